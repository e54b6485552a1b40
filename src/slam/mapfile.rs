//! The map file: a versioned little-endian binary format.
//!
//! ```text
//! magic    8 bytes  "SHOTMAP\0"
//! version  u32      (FORMAT_VERSION)
//! length   u64      payload bytes
//! checksum u64      FNV-1a 64 of the payload
//! payload           camera, scale, keyframes (pose, keypoints, descriptors,
//!                   point slots, covisibility, parent, image), points
//!                   (position, descriptor, normal, scale range, counters,
//!                   observations), culled keyframes, loop edges
//!                   (version 3: pairs of live keyframe ids), maps
//!                   (version 4: the active map id, then the map id of
//!                   every live and culled keyframe), mode (version 5:
//!                   u8, 0 vision-only, 1 gps-aided)
//! ```
//!
//! Keyframe images are stored so that they load back pixel for pixel
//! (version 2): the bytes the video delivered when they decode to exactly
//! the keyframe's image (the daemon's JPEG frames, see [`KeyframeImages`]),
//! else PNG. Version 1 stored a JPEG re-encoded at quality 90, a second
//! lossy generation of the video frame (and one more at every save of a
//! continued map): an anchors shot, which warps the keyframe's image,
//! then matched the map with different pixels than before the save (up to
//! 0.4 px more reprojection RMSE). Version 1 files are still read.
//!
//! Version 3 appends the loop edges of the essential graph (the keyframe
//! pairs loop closing joined, [`Map::loop_edges`]): a reloaded map keeps
//! them, so its loop keyframes stay uncullable and a later loop's
//! essential graph holds the earlier loops. Version 1 and 2 files load with
//! no loop edges (they were written before loop closing existed).
//!
//! Version 4 appends the atlas: which map each keyframe belongs to and
//! which map is active. A map merged before the save is one map; a new map
//! started after a tracking loss and not merged yet is saved as it is,
//! beside the old one (the next run relocalises into either and can merge
//! them when it sees a common place). Files of versions 1 to 3 load as one
//! map (id 0). A keyframe listed twice, missing, or not in the file, and
//! maps linked by a covisibility edge, a parent or a point are refused.
//!
//! Version 5 appends the map's mode ([`MapMode`]): a map put in local NED
//! by telemetry priors loads back gps-aided, so a continued map keeps its
//! frame (and the daemon's georeference keeps following from it). Files of
//! versions 1 to 4 load vision-only; any other mode byte is refused.
//!
//! The camera's rolling-shutter readout is not stored: a map loads as a
//! global shutter's, and the daemon continuing it gives it `[camera]`'s.
//!
//! Loading checks the magic, the version, the length and the checksum, every
//! index, and the map's invariants; any failure is a typed error.

use std::collections::HashMap;
use std::io::Write as _;
use std::path::{Path, PathBuf};
use std::sync::Arc;

use image::GrayImage;

use nalgebra::{Isometry3, Point3, Quaternion, Translation3, UnitQuaternion, Vector3};

use crate::camera::{Camera, Distortion};
use crate::features::KeyPoint;

use super::map::{
    CulledKeyFrame, KeyFrame, KeyFrameId, Map, MapError, MapId, MapMode, MapPoint, PointId,
    ScaleInfo,
};
use crate::matching::{Bounds, FeatureGrid};

/// The format version this build writes (it also reads versions 1 to 4).
pub const FORMAT_VERSION: u32 = 5;
/// The oldest version this build reads.
pub const OLDEST_VERSION: u32 = 1;
const MAGIC: &[u8; 8] = b"SHOTMAP\0";

/// Errors reading or writing a map file.
#[derive(Debug, thiserror::Error)]
pub enum MapFileError {
    /// The file could not be read or written.
    #[error("cannot access map file {path}: {source}")]
    Io {
        /// The file.
        path: PathBuf,
        /// The cause.
        source: std::io::Error,
    },
    /// Not a shotpilot map file.
    #[error("{path}: not a shotpilot map file (bad magic)")]
    BadMagic {
        /// The file.
        path: PathBuf,
    },
    /// A map file of another format version.
    #[error("{path}: map format version {found}, this build reads version {supported}")]
    Version {
        /// The file.
        path: PathBuf,
        /// Version in the file.
        found: u32,
        /// Version this build reads.
        supported: u32,
    },
    /// The content is damaged.
    #[error("{path}: corrupt map file: {reason}")]
    Corrupt {
        /// The file.
        path: PathBuf,
        /// What is wrong.
        reason: Corruption,
    },
    /// A keyframe image could not be encoded.
    #[error("cannot encode keyframe image: {0}")]
    Encode(String),
}

/// What is wrong inside a damaged map file (the reason of
/// [`MapFileError::Corrupt`]); byte offsets count from the payload's start
/// (after the 28-byte header) except in the header's own errors.
#[derive(Debug, thiserror::Error)]
pub enum Corruption {
    /// Shorter than the 28-byte header.
    #[error("header truncated")]
    HeaderTruncated,
    /// The payload's length is not the header's.
    #[error("payload is {found} bytes, header says {expected}")]
    PayloadLength {
        /// Bytes after the header.
        found: usize,
        /// Bytes the header announces.
        expected: usize,
    },
    /// The payload's FNV-1a checksum is not the header's.
    #[error("checksum mismatch")]
    Checksum,
    /// A length that overflows the address space.
    #[error("length overflow")]
    LengthOverflow,
    /// The data ends inside a field.
    #[error("truncated at byte {at}")]
    Truncated {
        /// Where the field starts.
        at: usize,
    },
    /// A NaN where a number is stored.
    #[error("NaN at byte {at}")]
    NaN {
        /// Where the number starts.
        at: usize,
    },
    /// A count larger than the remaining bytes could hold.
    #[error("count {count} at byte {at} exceeds the file")]
    Count {
        /// The count.
        count: usize,
        /// Where it is stored.
        at: usize,
    },
    /// A pose whose quaternion is not of unit norm.
    #[error("pose quaternion is not unit")]
    NotUnitQuaternion,
    /// The stored camera is not a valid camera.
    #[error(transparent)]
    Camera(#[from] crate::camera::CameraError),
    /// The ORB scale pyramid is impossible.
    #[error("bad scale levels ({scale_factor}, {levels})")]
    ScaleLevels {
        /// Scale between levels.
        scale_factor: f64,
        /// Number of levels.
        levels: usize,
    },
    /// A keypoint on a level the pyramid does not have.
    #[error("keypoint octave {octave} >= {levels} levels")]
    Octave {
        /// The keypoint's level.
        octave: u8,
        /// Levels of the pyramid.
        levels: usize,
    },
    /// A keyframe image that does not decode.
    #[error("keyframe {keyframe} image: {source}")]
    KeyframeImage {
        /// The keyframe.
        keyframe: u32,
        /// The decoder's error.
        source: image::ImageError,
    },
    /// A keyframe image of another size than the camera's.
    #[error(
        "keyframe {keyframe} image is {width}x{height}, the camera's {camera_width}x{camera_height}"
    )]
    KeyframeImageSize {
        /// The keyframe.
        keyframe: u32,
        /// Its image's width, pixels.
        width: u32,
        /// Its image's height, pixels.
        height: u32,
        /// The camera's width, pixels.
        camera_width: u32,
        /// The camera's height, pixels.
        camera_height: u32,
    },
    /// A loop edge whose keyframes are not two live keyframes.
    #[error("loop edge {a} - {b} does not join two live keyframes")]
    LoopEdge {
        /// One keyframe id.
        a: u32,
        /// The other.
        b: u32,
    },
    /// The atlas section does not give each live and culled keyframe
    /// exactly one map.
    #[error("keyframe {keyframe}: {what} in the maps section")]
    KeyFrameMap {
        /// The keyframe id.
        keyframe: u32,
        /// What is wrong ("listed twice", "not in the file", "missing").
        what: &'static str,
    },
    /// The mode byte is neither vision-only (0) nor gps-aided (1).
    #[error("map mode {0} is not 0 (vision-only) or 1 (gps-aided)")]
    Mode(u8),
    /// Bytes after the last section.
    #[error("{0} trailing bytes")]
    TrailingBytes(usize),
    /// The parts do not make a consistent map.
    #[error(transparent)]
    Map(#[from] MapError),
}

/// The stored bytes of keyframe images (JPEG or PNG), each known to decode
/// to exactly its keyframe's image; kept between saves so that an image is
/// encoded (or checked) once, and a loaded map is saved again with the
/// bytes it was loaded from (no generation loss).
#[derive(Debug, Clone, Default)]
pub struct KeyframeImages {
    bytes: HashMap<KeyFrameId, Arc<Vec<u8>>>,
}

/// The grey image that stored image bytes decode to (JPEG or PNG; colour
/// is converted as the video ingest converts it).
pub fn decode_image(bytes: &[u8]) -> Result<GrayImage, image::ImageError> {
    image::load_from_memory(bytes).map(|i| i.to_luma8())
}

/// A lossless PNG of a grey image.
fn png(img: &GrayImage) -> Result<Vec<u8>, MapFileError> {
    let mut out = Vec::new();
    image::codecs::png::PngEncoder::new_with_quality(
        &mut out,
        image::codecs::png::CompressionType::Fast,
        image::codecs::png::FilterType::Adaptive,
    )
    .write_image(
        img.as_raw(),
        img.width(),
        img.height(),
        image::ExtendedColorType::L8,
    )
    .map_err(|e| MapFileError::Encode(e.to_string()))?;
    Ok(out)
}

use image::ImageEncoder as _;

impl KeyframeImages {
    /// Offers the bytes a keyframe's image was decoded from (the video's
    /// JPEG): kept when they decode to exactly `image`, so the file stores
    /// them instead of a PNG. Returns whether they were kept.
    pub fn offer(&mut self, id: KeyFrameId, bytes: Arc<Vec<u8>>, image: &GrayImage) -> bool {
        match decode_image(&bytes) {
            Ok(decoded) if decoded == *image => {
                self.bytes.insert(id, bytes);
                true
            }
            _ => false,
        }
    }

    /// The stored bytes of a keyframe's image, when known.
    pub fn get(&self, id: KeyFrameId) -> Option<&Arc<Vec<u8>>> {
        self.bytes.get(&id)
    }

    /// Images held.
    pub fn len(&self) -> usize {
        self.bytes.len()
    }

    /// True when none is held.
    pub fn is_empty(&self) -> bool {
        self.bytes.is_empty()
    }

    /// Forgets the images of keyframes that are no longer in `map`.
    pub fn retain_in(&mut self, map: &Map) {
        self.bytes.retain(|id, _| map.keyframe(*id).is_some());
    }

    /// The bytes to store for `kf`'s image: the known ones, else a PNG
    /// (remembered).
    fn bytes_for(&mut self, id: KeyFrameId, img: &GrayImage) -> Result<Arc<Vec<u8>>, MapFileError> {
        if let Some(b) = self.bytes.get(&id) {
            return Ok(b.clone());
        }
        let b = Arc::new(png(img)?);
        self.bytes.insert(id, b.clone());
        Ok(b)
    }
}

/// FNV-1a, 64 bit.
fn fnv1a(data: &[u8]) -> u64 {
    let mut h: u64 = 0xcbf2_9ce4_8422_2325;
    for &b in data {
        h ^= b as u64;
        h = h.wrapping_mul(0x0000_0100_0000_01b3);
    }
    h
}

struct W(Vec<u8>);

impl W {
    fn u8(&mut self, v: u8) {
        self.0.push(v);
    }
    fn u32(&mut self, v: u32) {
        self.0.extend_from_slice(&v.to_le_bytes());
    }
    fn u64(&mut self, v: u64) {
        self.0.extend_from_slice(&v.to_le_bytes());
    }
    fn f32(&mut self, v: f32) {
        self.0.extend_from_slice(&v.to_le_bytes());
    }
    fn f64(&mut self, v: f64) {
        self.0.extend_from_slice(&v.to_le_bytes());
    }
    fn opt_u32(&mut self, v: Option<u32>) {
        self.u32(v.map_or(u32::MAX, |x| x));
    }
    fn pose(&mut self, p: &Isometry3<f64>) {
        let t = p.translation.vector;
        let q = p.rotation.coords;
        for v in [t.x, t.y, t.z, q.x, q.y, q.z, q.w] {
            self.f64(v);
        }
    }
    fn len(&mut self, n: usize) {
        self.u32(n as u32);
    }
}

struct R<'a> {
    data: &'a [u8],
    pos: usize,
}

type RResult<T> = Result<T, Corruption>;

impl<'a> R<'a> {
    fn take(&mut self, n: usize) -> RResult<&'a [u8]> {
        let end = self.pos.checked_add(n).ok_or(Corruption::LengthOverflow)?;
        let s = self
            .data
            .get(self.pos..end)
            .ok_or(Corruption::Truncated { at: self.pos })?;
        self.pos = end;
        Ok(s)
    }
    fn u8(&mut self) -> RResult<u8> {
        Ok(self.take(1)?[0])
    }
    fn u32(&mut self) -> RResult<u32> {
        let mut b = [0u8; 4];
        b.copy_from_slice(self.take(4)?);
        Ok(u32::from_le_bytes(b))
    }
    fn u64(&mut self) -> RResult<u64> {
        let mut b = [0u8; 8];
        b.copy_from_slice(self.take(8)?);
        Ok(u64::from_le_bytes(b))
    }
    fn f32(&mut self) -> RResult<f32> {
        let mut b = [0u8; 4];
        b.copy_from_slice(self.take(4)?);
        Ok(f32::from_le_bytes(b))
    }
    fn f64(&mut self) -> RResult<f64> {
        let mut b = [0u8; 8];
        b.copy_from_slice(self.take(8)?);
        let v = f64::from_le_bytes(b);
        if v.is_nan() {
            return Err(Corruption::NaN { at: self.pos - 8 });
        }
        Ok(v)
    }
    fn opt_u32(&mut self) -> RResult<Option<u32>> {
        let v = self.u32()?;
        Ok((v != u32::MAX).then_some(v))
    }
    /// A count, bounded by what the remaining bytes could hold.
    fn len(&mut self, min_item_bytes: usize) -> RResult<usize> {
        let n = self.u32()? as usize;
        let remaining = self.data.len() - self.pos;
        if n.saturating_mul(min_item_bytes.max(1)) > remaining {
            return Err(Corruption::Count {
                count: n,
                at: self.pos - 4,
            });
        }
        Ok(n)
    }
    fn pose(&mut self) -> RResult<Isometry3<f64>> {
        let mut v = [0.0; 7];
        for x in &mut v {
            *x = self.f64()?;
        }
        let q = Quaternion::new(v[6], v[3], v[4], v[5]);
        if (q.norm() - 1.0).abs() > 1e-6 {
            return Err(Corruption::NotUnitQuaternion);
        }
        Ok(Isometry3::from_parts(
            Translation3::new(v[0], v[1], v[2]),
            UnitQuaternion::new_unchecked(q),
        ))
    }
}

/// Serialise a map; keyframe images as PNG (see [`encode_with`]).
pub fn encode(map: &Map) -> Result<Vec<u8>, MapFileError> {
    encode_with(map, &mut KeyframeImages::default())
}

/// Serialise a map, storing each keyframe image as the bytes `images`
/// holds for it (else a PNG, which `images` then keeps for the next save).
pub fn encode_with(map: &Map, images: &mut KeyframeImages) -> Result<Vec<u8>, MapFileError> {
    let mut w = W(Vec::with_capacity(1 << 20));
    let c = &map.camera;
    w.u32(c.width);
    w.u32(c.height);
    let d = c.distortion;
    for v in [c.fx, c.fy, c.cx, c.cy, d.k1, d.k2, d.p1, d.p2, d.k3] {
        w.f64(v);
    }
    w.f64(map.scale.scale_factor);
    w.len(map.scale.n_levels());
    w.u32(map.covisibility_threshold);
    let kfs: Vec<&KeyFrame> = map.keyframes().collect();
    w.len(kfs.len());
    for k in kfs {
        w.u32(k.id.0);
        w.u64(k.frame_index);
        w.f64(k.timestamp);
        w.pose(&k.cam_from_world);
        w.opt_u32(k.parent.map(|p| p.0));
        w.len(k.keypoints.len());
        for (i, kp) in k.keypoints.iter().enumerate() {
            for v in [kp.x, kp.y, kp.ux, kp.uy, kp.angle, kp.size, kp.response] {
                w.f32(v);
            }
            w.u8(kp.octave);
            for word in k.descriptors[i] {
                w.u64(word);
            }
            w.opt_u32(k.points[i].map(|p| p.0));
        }
        w.len(k.covisible.len());
        for (o, wt) in &k.covisible {
            w.u32(o.0);
            w.u32(*wt);
        }
        w.len(k.children.len());
        for ch in &k.children {
            w.u32(ch.0);
        }
        match &k.image {
            Some(img) => {
                let bytes = images.bytes_for(k.id, img)?;
                w.len(bytes.len());
                w.0.extend_from_slice(&bytes);
            }
            None => w.len(0),
        }
    }
    let pts: Vec<&MapPoint> = map.points().collect();
    w.len(pts.len());
    for p in pts {
        w.u32(p.id.0);
        for v in [
            p.position.x,
            p.position.y,
            p.position.z,
            p.normal.x,
            p.normal.y,
            p.normal.z,
            p.min_distance,
            p.max_distance,
        ] {
            w.f64(v);
        }
        for word in p.descriptor {
            w.u64(word);
        }
        w.u32(p.first_kf.0);
        w.u32(p.ref_kf.0);
        w.u32(p.visible);
        w.u32(p.found);
        w.len(p.observations.len());
        for (kf, i) in &p.observations {
            w.u32(kf.0);
            w.u32(*i);
        }
    }
    let mut culled: Vec<(&KeyFrameId, &CulledKeyFrame)> = map.culled.iter().collect();
    culled.sort_by_key(|c| c.0);
    w.len(culled.len());
    for (id, c) in culled {
        w.u32(id.0);
        w.u32(c.parent.0);
        w.pose(&c.cam_from_parent);
    }
    let edges = map.loop_edges();
    w.len(edges.len());
    for (a, b) in edges {
        w.u32(a.0);
        w.u32(b.0);
    }
    w.u32(map.active_map().0);
    let maps = map.keyframe_maps();
    w.len(maps.len());
    for (kf, m) in maps {
        w.u32(kf.0);
        w.u32(m.0);
    }
    w.u8(match map.mode() {
        MapMode::VisionOnly => 0,
        MapMode::GpsAided => 1,
    });
    Ok(framed(FORMAT_VERSION, &w.0))
}

/// A file's bytes: the header (magic, `version`, the payload's length and
/// checksum) and the payload.
fn framed(version: u32, payload: &[u8]) -> Vec<u8> {
    let mut out = Vec::with_capacity(payload.len() + 28);
    out.extend_from_slice(MAGIC);
    out.extend_from_slice(&version.to_le_bytes());
    out.extend_from_slice(&(payload.len() as u64).to_le_bytes());
    out.extend_from_slice(&fnv1a(payload).to_le_bytes());
    out.extend_from_slice(payload);
    out
}

/// The temporary file a save writes before renaming it into place
/// (`<name>.tmp` beside `path`); a leftover one is an interrupted save.
pub fn temp_path(path: &Path) -> PathBuf {
    beside(path, ".tmp")
}

/// `<name><suffix>` beside `path` (`map.spmap` + `.tmp`: `map.spmap.tmp`).
pub fn beside(path: &Path, suffix: &str) -> PathBuf {
    let name = path
        .file_name()
        .map(|n| n.to_string_lossy().into_owned())
        .unwrap_or_else(|| "map".into());
    path.with_file_name(format!("{name}{suffix}"))
}

/// Write a map file (keyframe images as PNG, see [`save_with`]).
pub fn save(map: &Map, path: &Path) -> Result<(), MapFileError> {
    save_with(map, path, &mut KeyframeImages::default())
}

/// Write a map file atomically (a temporary file, flushed to disk, renamed
/// into place), its keyframe images as [`encode_with`] stores them.
pub fn save_with(map: &Map, path: &Path, images: &mut KeyframeImages) -> Result<(), MapFileError> {
    let bytes = encode_with(map, images)?;
    let tmp = temp_path(path);
    let io = |source| MapFileError::Io {
        path: path.to_owned(),
        source,
    };
    {
        let mut f = std::fs::File::create(&tmp).map_err(io)?;
        f.write_all(&bytes).map_err(io)?;
        f.sync_all().map_err(io)?;
    }
    std::fs::rename(&tmp, path).map_err(io)
}

/// Read a map file.
pub fn load(path: &Path) -> Result<Map, MapFileError> {
    load_with_images(path).map(|(m, _)| m)
}

/// Read a map file, with the stored bytes of its keyframe images (to save
/// the map again without re-encoding them).
pub fn load_with_images(path: &Path) -> Result<(Map, KeyframeImages), MapFileError> {
    let bytes = std::fs::read(path).map_err(|source| MapFileError::Io {
        path: path.to_owned(),
        source,
    })?;
    decode_with_images(&bytes, path)
}

/// Parse map file bytes; `path` names the source in errors.
pub fn decode(bytes: &[u8], path: &Path) -> Result<Map, MapFileError> {
    decode_with_images(bytes, path).map(|(m, _)| m)
}

/// [`decode`], with the stored bytes of the keyframe images.
pub fn decode_with_images(
    bytes: &[u8],
    path: &Path,
) -> Result<(Map, KeyframeImages), MapFileError> {
    let corrupt = |reason: Corruption| MapFileError::Corrupt {
        path: path.to_owned(),
        reason,
    };
    if bytes.len() < 8 || &bytes[..8] != MAGIC {
        return Err(MapFileError::BadMagic {
            path: path.to_owned(),
        });
    }
    if bytes.len() < 28 {
        return Err(corrupt(Corruption::HeaderTruncated));
    }
    let mut hdr = R {
        data: bytes,
        pos: 8,
    };
    let version = hdr.u32().map_err(&corrupt)?;
    if !(OLDEST_VERSION..=FORMAT_VERSION).contains(&version) {
        return Err(MapFileError::Version {
            path: path.to_owned(),
            found: version,
            supported: FORMAT_VERSION,
        });
    }
    let len = hdr.u64().map_err(&corrupt)? as usize;
    let sum = hdr.u64().map_err(&corrupt)?;
    let payload = &bytes[28..];
    if payload.len() != len {
        return Err(corrupt(Corruption::PayloadLength {
            found: payload.len(),
            expected: len,
        }));
    }
    if fnv1a(payload) != sum {
        return Err(corrupt(Corruption::Checksum));
    }
    parse_payload(payload, version).map_err(corrupt)
}

fn parse_payload(payload: &[u8], version: u32) -> RResult<(Map, KeyframeImages)> {
    let mut r = R {
        data: payload,
        pos: 0,
    };
    let (width, height) = (r.u32()?, r.u32()?);
    let mut v = [0.0; 9];
    for x in &mut v {
        *x = r.f64()?;
    }
    let camera = Camera::new(
        width,
        height,
        [v[0], v[1], v[2], v[3]],
        Distortion {
            k1: v[4],
            k2: v[5],
            p1: v[6],
            p2: v[7],
            k3: v[8],
        },
    )?;
    let scale_factor = r.f64()?;
    let n_levels = r.len(0)?;
    if !(scale_factor > 1.0 && (1..=32).contains(&n_levels)) {
        return Err(Corruption::ScaleLevels {
            scale_factor,
            levels: n_levels,
        });
    }
    let scale = ScaleInfo::new(scale_factor, n_levels);
    let covis_th = r.u32()?;
    let bounds = Bounds::of(&camera);
    let n_kf = r.len(60)?;
    let mut keyframes = Vec::with_capacity(n_kf);
    let mut images = KeyframeImages::default();
    for _ in 0..n_kf {
        let id = KeyFrameId(r.u32()?);
        let frame_index = r.u64()?;
        let timestamp = r.f64()?;
        let cam_from_world = r.pose()?;
        let parent = r.opt_u32()?.map(KeyFrameId);
        let n_kp = r.len(4 * 7 + 1 + 32 + 4)?;
        let mut keypoints = Vec::with_capacity(n_kp);
        let mut descriptors = Vec::with_capacity(n_kp);
        let mut points = Vec::with_capacity(n_kp);
        for _ in 0..n_kp {
            let mut f = [0f32; 7];
            for x in &mut f {
                *x = r.f32()?;
            }
            let octave = r.u8()?;
            if octave as usize >= n_levels {
                return Err(Corruption::Octave {
                    octave,
                    levels: n_levels,
                });
            }
            keypoints.push(KeyPoint {
                x: f[0],
                y: f[1],
                ux: f[2],
                uy: f[3],
                angle: f[4],
                size: f[5],
                response: f[6],
                octave,
            });
            descriptors.push([r.u64()?, r.u64()?, r.u64()?, r.u64()?]);
            points.push(r.opt_u32()?.map(PointId));
        }
        let n_cov = r.len(8)?;
        let mut covisible = Vec::with_capacity(n_cov);
        for _ in 0..n_cov {
            covisible.push((KeyFrameId(r.u32()?), r.u32()?));
        }
        let n_ch = r.len(4)?;
        let mut children = Vec::with_capacity(n_ch);
        for _ in 0..n_ch {
            children.push(KeyFrameId(r.u32()?));
        }
        let n_image = r.len(1)?;
        let image = if n_image > 0 {
            let stored = r.take(n_image)?;
            let img = decode_image(stored).map_err(|source| Corruption::KeyframeImage {
                keyframe: id.0,
                source,
            })?;
            if img.dimensions() != (width, height) {
                return Err(Corruption::KeyframeImageSize {
                    keyframe: id.0,
                    width: img.width(),
                    height: img.height(),
                    camera_width: width,
                    camera_height: height,
                });
            }
            images.bytes.insert(id, Arc::new(stored.to_vec()));
            Some(Arc::new(img))
        } else {
            None
        };
        let grid = FeatureGrid::new(&keypoints, bounds);
        keyframes.push(KeyFrame {
            id,
            frame_index,
            timestamp,
            cam_from_world,
            keypoints,
            descriptors,
            points,
            grid,
            covisible,
            parent,
            children,
            image,
        });
    }
    let n_p = r.len(4 + 64 + 32 + 20)?;
    let mut points = Vec::with_capacity(n_p);
    for _ in 0..n_p {
        let id = PointId(r.u32()?);
        let mut f = [0.0; 8];
        for x in &mut f {
            *x = r.f64()?;
        }
        let descriptor = [r.u64()?, r.u64()?, r.u64()?, r.u64()?];
        let first_kf = KeyFrameId(r.u32()?);
        let ref_kf = KeyFrameId(r.u32()?);
        let visible = r.u32()?;
        let found = r.u32()?;
        let n_obs = r.len(8)?;
        let mut observations = Vec::with_capacity(n_obs);
        for _ in 0..n_obs {
            observations.push((KeyFrameId(r.u32()?), r.u32()?));
        }
        points.push(MapPoint {
            id,
            position: Point3::new(f[0], f[1], f[2]),
            normal: Vector3::new(f[3], f[4], f[5]),
            min_distance: f[6],
            max_distance: f[7],
            observations,
            descriptor,
            first_kf,
            ref_kf,
            visible,
            found,
        });
    }
    let n_c = r.len(64)?;
    let mut culled = Vec::with_capacity(n_c);
    for _ in 0..n_c {
        let id = KeyFrameId(r.u32()?);
        let parent = KeyFrameId(r.u32()?);
        let cam_from_parent = r.pose()?;
        culled.push((
            id,
            CulledKeyFrame {
                parent,
                cam_from_parent,
            },
        ));
    }
    let mut loop_edges = Vec::new();
    if version >= 3 {
        let n_l = r.len(8)?;
        for _ in 0..n_l {
            loop_edges.push((r.u32()?, r.u32()?));
        }
    }
    let mut atlas = None;
    if version >= 4 {
        let active = MapId(r.u32()?);
        let n_m = r.len(8)?;
        let mut maps = Vec::with_capacity(n_m);
        for _ in 0..n_m {
            maps.push((KeyFrameId(r.u32()?), MapId(r.u32()?)));
        }
        atlas = Some((active, maps));
    }
    let mut mode = MapMode::VisionOnly;
    if version >= 5 {
        mode = match r.u8()? {
            0 => MapMode::VisionOnly,
            1 => MapMode::GpsAided,
            other => return Err(Corruption::Mode(other)),
        };
    }
    if r.pos != payload.len() {
        return Err(Corruption::TrailingBytes(payload.len() - r.pos));
    }
    let mut map = Map::from_parts(camera, scale, covis_th, keyframes, points, culled)?;
    if let Some((active, maps)) = atlas {
        let mut seen = std::collections::HashSet::new();
        for (kf, _) in &maps {
            let what = if map.keyframe(*kf).is_none() && !map.culled.contains_key(kf) {
                Some("not in the file")
            } else if !seen.insert(*kf) {
                Some("listed twice")
            } else {
                None
            };
            if let Some(what) = what {
                return Err(Corruption::KeyFrameMap {
                    keyframe: kf.0,
                    what,
                });
            }
        }
        let missing = map
            .keyframes()
            .map(|k| k.id)
            .chain(map.culled.keys().copied())
            .find(|k| !seen.contains(k));
        if let Some(kf) = missing {
            return Err(Corruption::KeyFrameMap {
                keyframe: kf.0,
                what: "missing",
            });
        }
        map.set_keyframe_maps(&maps, active);
    }
    for (a, b) in loop_edges {
        if !map.add_loop_edge(KeyFrameId(a), KeyFrameId(b)) {
            return Err(Corruption::LoopEdge { a, b });
        }
    }
    map.set_mode(mode);
    map.check_invariants()?;
    Ok((map, images))
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::camera::Distortion;
    use crate::matching::{Bounds, FeatureGrid};

    /// A one-keyframe map whose image is a noisy texture (what JPEG
    /// changes).
    fn map_with_image() -> (Map, GrayImage) {
        let camera = Camera::new(64, 48, [50.0, 50.0, 31.5, 23.5], Distortion::default()).unwrap();
        let img = GrayImage::from_fn(64, 48, |x, y| {
            image::Luma([((x * 37 + y * 91 + (x * y) % 13 * 17) % 256) as u8])
        });
        let kf = KeyFrame {
            id: KeyFrameId(0),
            frame_index: 7,
            timestamp: 1.5,
            cam_from_world: Isometry3::identity(),
            keypoints: Vec::new(),
            descriptors: Vec::new(),
            points: Vec::new(),
            grid: FeatureGrid::new(&[], Bounds::of(&camera)),
            covisible: Vec::new(),
            parent: None,
            children: Vec::new(),
            image: Some(Arc::new(img.clone())),
        };
        let map = Map::from_parts(
            camera,
            ScaleInfo::new(1.2, 8),
            15,
            vec![kf],
            Vec::new(),
            Vec::new(),
        )
        .unwrap();
        (map, img)
    }

    #[test]
    fn keyframe_images_come_back_pixel_for_pixel() {
        let (map, img) = map_with_image();
        let p = Path::new("mem");
        // PNG when nothing else is known.
        let (back, images) = decode_with_images(&encode(&map).unwrap(), p).unwrap();
        let got = back.keyframe(KeyFrameId(0)).unwrap().image.clone().unwrap();
        assert_eq!(*got, img);
        // The video's JPEG is stored as it came when it decodes to the image.
        let mut jpeg = Vec::new();
        image::codecs::jpeg::JpegEncoder::new_with_quality(&mut jpeg, 80)
            .encode_image(&img)
            .unwrap();
        let decoded = decode_image(&jpeg).unwrap();
        assert_ne!(decoded, img, "JPEG changes this texture");
        let mut jpeg_map = map.clone();
        jpeg_map.keyframe_mut(KeyFrameId(0)).unwrap().image = Some(Arc::new(decoded.clone()));
        let mut known = KeyframeImages::default();
        assert!(
            !known.offer(KeyFrameId(0), Arc::new(jpeg.clone()), &img),
            "not its source"
        );
        assert!(known.offer(KeyFrameId(0), Arc::new(jpeg.clone()), &decoded));
        let bytes = encode_with(&jpeg_map, &mut known).unwrap();
        let (back, images2) = decode_with_images(&bytes, p).unwrap();
        assert_eq!(
            **images2.get(KeyFrameId(0)).unwrap(),
            jpeg,
            "stored as it came"
        );
        assert_eq!(
            *back.keyframe(KeyFrameId(0)).unwrap().image.clone().unwrap(),
            decoded
        );
        // Saved again from what was loaded: the same bytes, no new generation.
        let mut again = images2.clone();
        assert_eq!(encode_with(&back, &mut again).unwrap(), bytes);
        assert_eq!(images.len(), 1);
    }

    #[test]
    fn version_1_files_are_still_read() {
        let (map, img) = map_with_image();
        let mut jpeg = Vec::new();
        image::codecs::jpeg::JpegEncoder::new_with_quality(&mut jpeg, 90)
            .encode_image(&img)
            .unwrap();
        let mut known = KeyframeImages::default();
        let decoded = decode_image(&jpeg).unwrap();
        let mut m = map.clone();
        m.keyframe_mut(KeyFrameId(0)).unwrap().image = Some(Arc::new(decoded.clone()));
        assert!(known.offer(KeyFrameId(0), Arc::new(jpeg), &decoded));
        let mut v1 = before_version_3(&encode_with(&m, &mut known).unwrap(), 1, 1);
        let back = decode(&v1, Path::new("v1")).unwrap();
        assert_eq!(
            *back.keyframe(KeyFrameId(0)).unwrap().image.clone().unwrap(),
            decoded
        );
        v1[8..12].copy_from_slice(&(FORMAT_VERSION + 1).to_le_bytes());
        let found = FORMAT_VERSION + 1;
        assert!(matches!(
            decode(&v1, Path::new("v5")),
            Err(MapFileError::Version { found: f, .. }) if f == found
        ));
    }

    /// Bytes of the atlas section of a map with `n` live and culled
    /// keyframes (active map, count, one id pair each).
    fn atlas_len(n: usize) -> usize {
        8 + 8 * n
    }

    /// The file a version 3 build wrote: this build's bytes (of a map all
    /// in map 0, `n` live and culled keyframes) without the atlas section
    /// that version 4 appended, with the header's version, length and
    /// checksum of that payload.
    fn before_version_4(v5: &[u8], n: usize, version: u32) -> Vec<u8> {
        let v4 = before_version_5(v5, 4);
        let payload = &v4[28..];
        let (old, atlas) = payload.split_at(payload.len() - atlas_len(n));
        assert_eq!(&atlas[..4], &0u32.to_le_bytes(), "only maps all in map 0");
        framed(version, old)
    }

    /// The file a version 4 build wrote: this build's bytes of a
    /// vision-only map without the mode byte version 5 appended.
    fn before_version_5(v5: &[u8], version: u32) -> Vec<u8> {
        let payload = &v5[28..];
        let (old, mode) = payload.split_at(payload.len() - 1);
        assert_eq!(mode, &[0u8], "only vision-only maps");
        framed(version, old)
    }

    #[test]
    fn the_mode_loads_back_and_older_files_are_vision_only() {
        let mut m = two_keyframes();
        m.set_mode(MapMode::GpsAided);
        let bytes = encode(&m).unwrap();
        assert_eq!(bytes[8..12], 5u32.to_le_bytes());
        let back = decode(&bytes, Path::new("v5")).unwrap();
        assert_eq!(back.mode(), MapMode::GpsAided);
        assert_eq!(encode(&back).unwrap(), bytes);
        // A version 4 file (before the mode) loads vision-only.
        let v4 = before_version_5(&encode(&two_keyframes()).unwrap(), 4);
        let old = decode(&v4, Path::new("v4")).unwrap();
        assert_eq!(old.mode(), MapMode::VisionOnly);
        assert_eq!(old.keyframe_count(), 2);
        // An unknown mode byte is refused.
        let mut bad = bytes.clone();
        let last = bad.len() - 1;
        bad[last] = 7;
        assert!(matches!(
            decode(&with_checksum(bad), Path::new("bad mode")),
            Err(MapFileError::Corrupt {
                reason: Corruption::Mode(7),
                ..
            })
        ));
    }

    /// The file a version 1 or 2 build wrote for a map without loop edges
    /// (`n` live and culled keyframes): without the atlas and without the
    /// loop-edge section (version 3 appended it, the 4-byte count, after
    /// the culled keyframes).
    fn before_version_3(v4: &[u8], n: usize, version: u32) -> Vec<u8> {
        let v3 = before_version_4(v4, n, 3);
        let payload = &v3[28..];
        let (old, count) = payload.split_at(payload.len() - 4);
        assert_eq!(count, &0u32.to_le_bytes(), "only maps without loop edges");
        framed(version, old)
    }

    /// Rewrite the header's checksum after editing the payload (a damaged
    /// file that passes the checksum, so the parser itself must refuse it).
    fn with_checksum(mut bytes: Vec<u8>) -> Vec<u8> {
        let sum = fnv1a(&bytes[28..]);
        bytes[20..28].copy_from_slice(&sum.to_le_bytes());
        bytes
    }

    /// Two keyframes (ids 0 and 3) without images, no points.
    fn two_keyframes() -> Map {
        let (map, _) = map_with_image();
        let mut k0 = map.keyframe(KeyFrameId(0)).unwrap().clone();
        k0.image = None;
        let mut k3 = k0.clone();
        k3.id = KeyFrameId(3);
        k3.frame_index = 40;
        k3.timestamp = 9.0;
        k3.cam_from_world = Isometry3::translation(0.5, 0.0, 0.0);
        Map::from_parts(
            map.camera,
            ScaleInfo::new(1.2, 8),
            15,
            vec![k0, k3],
            Vec::new(),
            Vec::new(),
        )
        .unwrap()
    }

    /// [`two_keyframes`] joined by a loop edge.
    fn map_with_loop_edge() -> Map {
        let mut m = two_keyframes();
        assert!(m.add_loop_edge(KeyFrameId(3), KeyFrameId(0)));
        m
    }

    #[test]
    fn loop_edges_load_back_and_version_2_files_load_without_them() {
        let m = map_with_loop_edge();
        let bytes = encode(&m).unwrap();
        assert_eq!(bytes[8..12], FORMAT_VERSION.to_le_bytes());
        let back = decode(&bytes, Path::new("v5")).unwrap();
        assert_eq!(back.loop_edges(), &[(KeyFrameId(3), KeyFrameId(0))]);
        assert_eq!(back.keyframe_count(), 2);
        // Saved again: the same bytes.
        assert_eq!(encode(&back).unwrap(), bytes);

        // A version 2 file (written before loop edges existed) loads with none.
        let v2 = before_version_3(&encode(&two_keyframes()).unwrap(), 2, 2);
        let old = decode(&v2, Path::new("v2")).unwrap();
        assert!(old.loop_edges().is_empty());
        assert_eq!(old.keyframe_count(), 2);
        assert_eq!(
            old.keyframe(KeyFrameId(3)).unwrap().cam_from_world,
            m.keyframe(KeyFrameId(3)).unwrap().cam_from_world
        );
        // A version 3 file (written before the atlas) loads as one map.
        let v3 = before_version_4(&bytes, 2, 3);
        let old3 = decode(&v3, Path::new("v3")).unwrap();
        assert_eq!(old3.loop_edges(), back.loop_edges());
        assert_eq!(old3.maps(), vec![(MapId(0), 2)]);
        let mut v3_as_4 = v3.clone();
        v3_as_4[8..12].copy_from_slice(&4u32.to_le_bytes());
        assert!(matches!(
            decode(&v3_as_4, Path::new("v3 as v4")),
            Err(MapFileError::Corrupt {
                reason: Corruption::Truncated { .. },
                ..
            })
        ));
        // The same bytes announced as version 3 lack the loop section.
        let mut v2_as_3 = v2.clone();
        v2_as_3[8..12].copy_from_slice(&3u32.to_le_bytes());
        assert!(matches!(
            decode(&v2_as_3, Path::new("v2 as v3")),
            Err(MapFileError::Corrupt {
                reason: Corruption::Truncated { .. },
                ..
            })
        ));
    }

    #[test]
    fn damaged_loop_edges_are_refused() {
        // A version 3 file: the loop edges are its last section.
        let bytes = before_version_4(&encode(&map_with_loop_edge()).unwrap(), 2, 3);
        let n = bytes.len();
        // The last 8 bytes are the edge (3, 0), the 4 before them the count.
        let edit = |at: usize, v: u32| {
            let mut b = bytes.clone();
            b[at..at + 4].copy_from_slice(&v.to_le_bytes());
            with_checksum(b)
        };
        let corrupt = |b: &[u8]| match decode(b, Path::new("damaged")) {
            Err(MapFileError::Corrupt { reason, .. }) => reason,
            other => panic!(
                "not refused as corrupt: {:?}",
                other.map(|m| m.loop_edges().to_vec())
            ),
        };
        // An edge to a keyframe the map does not hold (1 is not live).
        assert!(matches!(
            corrupt(&edit(n - 4, 1)),
            Corruption::LoopEdge { a: 3, b: 1 }
        ));
        // An edge from a keyframe to itself.
        assert!(matches!(
            corrupt(&edit(n - 4, 3)),
            Corruption::LoopEdge { a: 3, b: 3 }
        ));
        // A count larger than the file.
        assert!(matches!(
            corrupt(&edit(n - 12, 1000)),
            Corruption::Count { .. }
        ));
        // Cut inside the section, with a header that matches the cut: the
        // count promises more than is left.
        let mut cut = bytes[..n - 4].to_vec();
        cut[12..20].copy_from_slice(&((n - 4 - 28) as u64).to_le_bytes());
        assert!(matches!(
            corrupt(&with_checksum(cut)),
            Corruption::Count { count: 1, .. }
        ));
        // A bit flipped without the checksum mended.
        let mut flipped = bytes.clone();
        flipped[n - 3] ^= 0x10;
        assert!(matches!(corrupt(&flipped), Corruption::Checksum));
    }

    /// [`two_keyframes`] in two maps (0 holds keyframe 0, 1 holds keyframe
    /// 3 and is active), as a new map after a loss is before it merges.
    fn two_maps() -> Map {
        let mut m = two_keyframes();
        m.set_keyframe_maps(
            &[(KeyFrameId(0), MapId(0)), (KeyFrameId(3), MapId(1))],
            MapId(1),
        );
        m
    }

    #[test]
    fn an_unmerged_map_is_saved_beside_the_old_one_and_a_damaged_atlas_is_refused() {
        let m = two_maps();
        m.check_invariants().unwrap();
        let bytes = encode(&m).unwrap();
        let back = decode(&bytes, Path::new("atlas")).unwrap();
        assert_eq!(back.maps(), vec![(MapId(0), 1), (MapId(1), 1)]);
        assert_eq!(back.active_map(), MapId(1));
        assert_eq!(back.root_of(MapId(0)), Some(KeyFrameId(0)));
        assert_eq!(back.root_of(MapId(1)), Some(KeyFrameId(3)));
        assert_eq!(encode(&back).unwrap(), bytes);
        // A map started after this one gets a new id.
        let mut more = back.clone();
        assert_eq!(more.start_map(), MapId(2));

        // The atlas ends before the mode byte.
        let n = bytes.len() - 1;
        let corrupt = |b: &[u8]| match decode(b, Path::new("damaged")) {
            Err(MapFileError::Corrupt { reason, .. }) => reason,
            other => panic!("not refused as corrupt: {:?}", other.map(|m| m.maps())),
        };
        // The last pair is (3, 1): its keyframe changed to one not in the
        // file, then to one listed already.
        let edit = |at: usize, v: u32| {
            let mut b = bytes.clone();
            b[at..at + 4].copy_from_slice(&v.to_le_bytes());
            with_checksum(b)
        };
        assert!(matches!(
            corrupt(&edit(n - 8, 1)),
            Corruption::KeyFrameMap {
                keyframe: 1,
                what: "not in the file"
            }
        ));
        assert!(matches!(
            corrupt(&edit(n - 8, 0)),
            Corruption::KeyFrameMap {
                keyframe: 0,
                what: "listed twice"
            }
        ));
        // The last pair dropped (count and header mended): keyframe 3 has
        // no map.
        let mut cut = bytes[..n - 8].to_vec();
        cut.push(0);
        let at = cut.len() - 13;
        cut[at..at + 4].copy_from_slice(&1u32.to_le_bytes());
        cut[12..20].copy_from_slice(&((n + 1 - 8 - 28) as u64).to_le_bytes());
        assert!(matches!(
            corrupt(&with_checksum(cut)),
            Corruption::KeyFrameMap {
                keyframe: 3,
                what: "missing"
            }
        ));
        // A count larger than the file.
        assert!(matches!(
            corrupt(&edit(n - 20, 1000)),
            Corruption::Count { .. }
        ));
        // Two maps joined by a parent link: refused by the invariants.
        let mut linked = two_keyframes();
        linked.keyframe_mut(KeyFrameId(3)).unwrap().parent = Some(KeyFrameId(0));
        linked
            .keyframe_mut(KeyFrameId(0))
            .unwrap()
            .children
            .push(KeyFrameId(3));
        linked.set_keyframe_maps(
            &[(KeyFrameId(0), MapId(0)), (KeyFrameId(3), MapId(1))],
            MapId(1),
        );
        assert!(matches!(
            corrupt(&encode(&linked).unwrap()),
            Corruption::Map(MapError::Invariant(
                crate::slam::map::Violation::CrossMap { .. }
            ))
        ));
    }
}
