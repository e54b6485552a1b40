//! The map file: a versioned little-endian binary format.
//!
//! ```text
//! magic    8 bytes  "SHOTMAP\0"
//! version  u32      (FORMAT_VERSION)
//! length   u64      payload bytes
//! checksum u64      FNV-1a 64 of the payload
//! payload           camera, scale, keyframes (pose, keypoints, descriptors,
//!                   point slots, covisibility, parent, JPEG image), points
//!                   (position, descriptor, normal, scale range, counters,
//!                   observations), culled keyframes
//! ```
//!
//! Loading checks the magic, the version, the length and the checksum, every
//! index, and the map's invariants; any failure is a typed error.

use std::path::{Path, PathBuf};
use std::sync::Arc;

use nalgebra::{Isometry3, Point3, Quaternion, Translation3, UnitQuaternion, Vector3};

use crate::camera::{Camera, Distortion};
use crate::features::KeyPoint;

use super::map::{CulledKeyFrame, KeyFrame, KeyFrameId, Map, MapPoint, PointId, ScaleInfo};
use crate::matching::{Bounds, FeatureGrid};

/// The format version this build writes and reads.
pub const FORMAT_VERSION: u32 = 1;
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
        reason: String,
    },
    /// A keyframe image could not be encoded.
    #[error("cannot encode keyframe image: {0}")]
    Encode(String),
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

type RResult<T> = Result<T, String>;

impl<'a> R<'a> {
    fn take(&mut self, n: usize) -> RResult<&'a [u8]> {
        let end = self.pos.checked_add(n).ok_or("length overflow")?;
        let s = self
            .data
            .get(self.pos..end)
            .ok_or_else(|| format!("truncated at byte {}", self.pos))?;
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
            return Err(format!("NaN at byte {}", self.pos - 8));
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
            return Err(format!(
                "count {n} at byte {} exceeds the file",
                self.pos - 4
            ));
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
            return Err("pose quaternion is not unit".into());
        }
        Ok(Isometry3::from_parts(
            Translation3::new(v[0], v[1], v[2]),
            UnitQuaternion::new_unchecked(q),
        ))
    }
}

/// Serialise a map (keyframe images as JPEG, quality 90).
pub fn encode(map: &Map) -> Result<Vec<u8>, MapFileError> {
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
                let mut jpeg = Vec::new();
                image::codecs::jpeg::JpegEncoder::new_with_quality(&mut jpeg, 90)
                    .encode_image(img.as_ref())
                    .map_err(|e| MapFileError::Encode(e.to_string()))?;
                w.len(jpeg.len());
                w.0.extend_from_slice(&jpeg);
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
    let payload = w.0;
    let mut out = Vec::with_capacity(payload.len() + 28);
    out.extend_from_slice(MAGIC);
    out.extend_from_slice(&FORMAT_VERSION.to_le_bytes());
    out.extend_from_slice(&(payload.len() as u64).to_le_bytes());
    out.extend_from_slice(&fnv1a(&payload).to_le_bytes());
    out.extend_from_slice(&payload);
    Ok(out)
}

/// Write a map file (atomically: a temporary file renamed into place).
pub fn save(map: &Map, path: &Path) -> Result<(), MapFileError> {
    let bytes = encode(map)?;
    let tmp = path.with_extension("tmp");
    let io = |source| MapFileError::Io {
        path: path.to_owned(),
        source,
    };
    std::fs::write(&tmp, &bytes).map_err(io)?;
    std::fs::rename(&tmp, path).map_err(io)
}

/// Read a map file.
pub fn load(path: &Path) -> Result<Map, MapFileError> {
    let bytes = std::fs::read(path).map_err(|source| MapFileError::Io {
        path: path.to_owned(),
        source,
    })?;
    decode(&bytes, path)
}

/// Parse map file bytes; `path` names the source in errors.
pub fn decode(bytes: &[u8], path: &Path) -> Result<Map, MapFileError> {
    let corrupt = |reason: String| MapFileError::Corrupt {
        path: path.to_owned(),
        reason,
    };
    if bytes.len() < 8 || &bytes[..8] != MAGIC {
        return Err(MapFileError::BadMagic {
            path: path.to_owned(),
        });
    }
    if bytes.len() < 28 {
        return Err(corrupt("header truncated".into()));
    }
    let mut hdr = R {
        data: bytes,
        pos: 8,
    };
    let version = hdr.u32().map_err(&corrupt)?;
    if version != FORMAT_VERSION {
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
        return Err(corrupt(format!(
            "payload is {} bytes, header says {len}",
            payload.len()
        )));
    }
    if fnv1a(payload) != sum {
        return Err(corrupt("checksum mismatch".into()));
    }
    parse_payload(payload).map_err(corrupt)
}

fn parse_payload(payload: &[u8]) -> RResult<Map> {
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
    )
    .map_err(|e| e.to_string())?;
    let scale_factor = r.f64()?;
    let n_levels = r.len(0)?;
    if !(scale_factor > 1.0 && (1..=32).contains(&n_levels)) {
        return Err(format!("bad scale levels ({scale_factor}, {n_levels})"));
    }
    let scale = ScaleInfo::new(scale_factor, n_levels);
    let covis_th = r.u32()?;
    let bounds = Bounds::of(&camera);
    let n_kf = r.len(60)?;
    let mut keyframes = Vec::with_capacity(n_kf);
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
                return Err(format!("keypoint octave {octave} >= {n_levels} levels"));
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
        let n_jpeg = r.len(1)?;
        let image = if n_jpeg > 0 {
            let jpeg = r.take(n_jpeg)?;
            let img = image::load_from_memory_with_format(jpeg, image::ImageFormat::Jpeg)
                .map_err(|e| format!("keyframe {} image: {e}", id.0))?
                .into_luma8();
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
    if r.pos != payload.len() {
        return Err(format!("{} trailing bytes", payload.len() - r.pos));
    }
    let map = Map::from_parts(camera, scale, covis_th, keyframes, points, culled)?;
    map.check_invariants()?;
    Ok(map)
}
