//! The camera as a physical imager: what happens between the scene and
//! the frame the ground station receives.
//!
//! [`Imager::capture`] takes the frame's time and the camera's true pose
//! as a function of time (the vehicle's and the gimbal's real motion,
//! jitter included), and:
//!
//! 1. exposes each row over its own interval: row `y` of `h` is exposed
//!    around `t_frame + (y - (h - 1) / 2) * readout / (h - 1)` (rolling
//!    shutter; the frame's time is the centre row's mid-exposure);
//! 2. integrates the scene over the exposure time (motion blur): the
//!    exposure is split into stratified sub-exposure samples, enough that
//!    the image moves at most `max_px_per_sample` between two, each
//!    rendered from the poses at its own time with the scene (moving cars,
//!    water, cloud shadows) at that time, averaged in linear light;
//! 3. turns scene light into signal: auto-exposure picks the exposure time
//!    and gain (with a lag: it meters the previous frames), lens vignetting
//!    dims the corners, the sensor adds photon shot noise and read noise,
//!    the signal clips at full scale;
//! 4. applies the camera's tone curve (display gamma) and quantises to 8
//!    bits;
//! 5. compresses the frame for the stream ([`FrameCodec`]: JPEG per frame
//!    as an MJPEG camera does, or H.264 through OpenH264 as an RTSP/RTP
//!    camera does, its predicted pictures and IDR pictures included) and
//!    returns the decoded frame, artefacts and all, with the encoded bytes.
//!
//! Ground truth stays exact: the returned [`Exposure`] holds the pose at
//! the frame's time (centre row, mid-exposure) and, with a rolling shutter,
//! the mid-exposure pose of every 16th row (and the last); the pose of any
//! row is the interpolation of its two neighbouring knots (linear in
//! translation, slerp in rotation, by row), which is exactly what the
//! renderer drew that row from.
//!
//! With every camera effect off (`ideal`), a capture is the plain
//! renderer's noisy frame at the frame's pose, bit for bit.

use std::sync::Arc;

use image::GrayImage;
use nalgebra::{Isometry3, Translation3};

use crate::realism::{CameraRealism, Compression, LightingRealism, clear_sky_illuminance_lux};
use crate::render::{Renderer, SceneState, gaussian};
use crate::texture::round_u8;
use crate::video::VideoError;

/// Rows between two rolling-shutter pose knots.
pub const ROW_KNOT_STEP: usize = 16;

/// The world's fixed sun (the `ideal` lighting): elevation, degrees.
pub const REFERENCE_SUN_ELEVATION_DEG: f64 = 50.0;

/// A stream codec: encodes a frame as the camera's stream would and
/// decodes it as the ground station would. JPEG (the MJPEG stream) or
/// H.264 (stateful across frames, hence `&mut self`).
pub trait FrameCodec: Send {
    /// Short description, e.g. `jpeg q50`.
    fn describe(&self) -> String;
    /// The encoded bytes and the decoded frame.
    fn transcode(&mut self, frame: &GrayImage) -> Result<(Vec<u8>, GrayImage), VideoError>;
    /// What the encoded bytes are.
    fn kind(&self) -> EncodedKind;
}

/// What a codec's bytes are.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum EncodedKind {
    /// A JPEG file.
    Jpeg,
    /// An H.264 access unit (Annex B).
    H264,
}

/// Baseline JPEG at a fixed quality (the MJPEG stream).
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct JpegCodec {
    /// IJG quality, 1-100.
    pub quality: u8,
}

impl FrameCodec for JpegCodec {
    fn describe(&self) -> String {
        format!("jpeg q{}", self.quality)
    }

    fn kind(&self) -> EncodedKind {
        EncodedKind::Jpeg
    }

    fn transcode(&mut self, frame: &GrayImage) -> Result<(Vec<u8>, GrayImage), VideoError> {
        let bytes = crate::video::try_encode_jpeg(frame, self.quality)?;
        let decoded = image::load_from_memory_with_format(&bytes, image::ImageFormat::Jpeg)
            .map_err(|source| VideoError::Encode {
                width: frame.width(),
                height: frame.height(),
                source,
            })?
            .to_luma8();
        Ok((bytes, decoded))
    }
}

/// H.264 through OpenH264 at a target bitrate (bitrate rate control, an
/// IDR picture every `idr_period` frames), decoded by OpenH264 as the
/// ground station decodes it: the frames in between are predicted from the
/// ones before, so the artefacts depend on the motion, as a real stream's.
pub struct H264Codec {
    /// Target bitrate, bits per second.
    pub bitrate_bps: u32,
    /// The encoder's frame rate, frames/s (its per-frame bit budget is
    /// `bitrate_bps / fps`).
    pub fps: f64,
    /// Frames between IDR pictures.
    pub idr_period: u32,
    enc: Option<crate::rtp::H264Encoder>,
    dec: Option<openh264::decoder::Decoder>,
    frames: u64,
}

impl H264Codec {
    /// A codec (the encoder starts with the first frame's size).
    pub fn new(bitrate_bps: u32, fps: f64, idr_period: u32) -> Self {
        Self {
            bitrate_bps,
            fps,
            idr_period,
            enc: None,
            dec: None,
            frames: 0,
        }
    }
}

impl std::fmt::Debug for H264Codec {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        f.write_str(&self.describe())
    }
}

fn h264_error(reason: String) -> VideoError {
    VideoError::H264 { reason }
}

impl FrameCodec for H264Codec {
    fn describe(&self) -> String {
        format!(
            "h264 {:.0} kbit/s at {} fps, IDR every {}",
            f64::from(self.bitrate_bps) / 1e3,
            self.fps,
            self.idr_period
        )
    }

    fn kind(&self) -> EncodedKind {
        EncodedKind::H264
    }

    fn transcode(&mut self, frame: &GrayImage) -> Result<(Vec<u8>, GrayImage), VideoError> {
        use openh264::formats::YUVSource;
        let (w, h) = frame.dimensions();
        if self
            .enc
            .as_ref()
            .is_none_or(|e| (e.width(), e.height()) != (w, h))
        {
            self.enc = Some(crate::rtp::H264Encoder::new(
                w,
                h,
                self.fps,
                self.bitrate_bps,
                self.idr_period,
            )?);
            self.dec = Some(
                openh264::decoder::Decoder::new()
                    .map_err(|e| h264_error(format!("starting the decoder: {e}")))?,
            );
        }
        let (Some(enc), Some(dec)) = (self.enc.as_mut(), self.dec.as_mut()) else {
            return Err(h264_error("no encoder".into()));
        };
        let ms = (self.frames as f64 * 1000.0 / self.fps.max(1e-3)) as u64;
        self.frames += 1;
        let bytes = enc.encode(frame, ms)?.annexb();
        let yuv = dec
            .decode(&bytes)
            .map_err(|e| h264_error(format!("decoding: {e}")))?
            .ok_or_else(|| h264_error("the decoder gave no picture".into()))?;
        let (dw, dh) = yuv.dimensions();
        let stride = yuv.strides().0;
        let y = yuv.y();
        if (dw, dh) != (w as usize, h as usize) || stride < dw || y.len() < stride * (dh - 1) + dw {
            return Err(h264_error(format!(
                "decoded {dw}x{dh} (stride {stride}) for a {w}x{h} frame"
            )));
        }
        let mut luma = Vec::with_capacity(dw * dh);
        for row in 0..dh {
            luma.extend_from_slice(&y[row * stride..row * stride + dw]);
        }
        let img =
            GrayImage::from_raw(w, h, luma).ok_or_else(|| h264_error("luma plane size".into()))?;
        Ok((bytes, img))
    }
}

/// The codec for a compression setting.
pub fn codec_for(c: &Compression) -> Box<dyn FrameCodec> {
    match *c {
        Compression::Jpeg { quality } => Box::new(JpegCodec { quality }),
        Compression::H264 {
            bitrate_bps,
            fps,
            idr_period,
        } => Box::new(H264Codec::new(bitrate_bps, fps, idr_period)),
    }
}

/// A rolling-shutter pose knot: the mid-exposure pose of one row.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct RowKnot {
    /// Image row.
    pub row: usize,
    /// Its mid-exposure time, seconds (the caller's clock).
    pub time_s: f64,
    /// The camera pose then.
    pub world_from_cam: Isometry3<f64>,
}

/// One captured frame with its exact ground truth.
#[derive(Debug, Clone)]
pub struct Exposure {
    /// The frame as the ground station decodes it.
    pub image: GrayImage,
    /// The encoded bytes (when a codec is on).
    pub encoded: Option<Vec<u8>>,
    /// What `encoded` is (when a codec is on).
    pub encoded_kind: Option<EncodedKind>,
    /// The frame's time: the centre row's mid-exposure, seconds.
    pub time_s: f64,
    /// The camera pose at `time_s`.
    pub world_from_cam: Isometry3<f64>,
    /// Exposure time, seconds (0 when the exposure is instantaneous).
    pub exposure_s: f64,
    /// Analogue gain (1 = base ISO).
    pub gain: f64,
    /// Rolling-shutter readout, seconds (0: global shutter).
    pub readout_s: f64,
    /// Mid-exposure pose knots of the rows (empty for a global shutter).
    pub row_knots: Vec<RowKnot>,
    /// Sub-exposure samples rendered.
    pub blur_samples: usize,
}

impl Exposure {
    /// The mid-exposure pose of row `y` (the interpolation of its knots;
    /// the frame's pose for a global shutter).
    pub fn row_pose(&self, y: usize) -> Isometry3<f64> {
        interpolate_knots(&self.row_knots, y).unwrap_or(self.world_from_cam)
    }
}

/// Interpolates knots (sorted by row) at row `y`: linear in translation and
/// slerp in rotation, by row. None without knots.
pub fn interpolate_knots(knots: &[RowKnot], y: usize) -> Option<Isometry3<f64>> {
    let first = knots.first()?;
    if knots.len() == 1 || y <= first.row {
        return Some(first.world_from_cam);
    }
    let i = knots.partition_point(|k| k.row <= y);
    if i >= knots.len() {
        return knots.last().map(|k| k.world_from_cam);
    }
    let (a, b) = (&knots[i - 1], &knots[i]);
    let f = (y - a.row) as f64 / (b.row - a.row).max(1) as f64;
    Some(lerp_pose(&a.world_from_cam, &b.world_from_cam, f))
}

/// Linear in translation, slerp in rotation, `f` in [0, 1] from `a` to `b`.
pub(crate) fn lerp_pose(a: &Isometry3<f64>, b: &Isometry3<f64>, f: f64) -> Isometry3<f64> {
    let t = a.translation.vector.lerp(&b.translation.vector, f);
    let q = a
        .rotation
        .try_slerp(&b.rotation, f, 1e-12)
        .unwrap_or(if f < 0.5 { a.rotation } else { b.rotation });
    Isometry3::from_parts(Translation3::from(t), q)
}

/// The rows that carry pose knots for an image of `height` rows.
pub fn knot_rows(height: usize) -> Vec<usize> {
    let mut rows: Vec<usize> = (0..height).step_by(ROW_KNOT_STEP).collect();
    if height > 0 && rows.last() != Some(&(height - 1)) {
        rows.push(height - 1);
    }
    rows
}

/// The auto-exposure's state.
#[derive(Debug, Clone, Copy, PartialEq)]
struct AeState {
    /// Exposure time x gain, seconds.
    product_s: f64,
    /// Time of the last frame metered.
    last_t: f64,
}

/// The camera between scene and stream (see the module documentation).
pub struct Imager {
    renderer: Arc<Renderer>,
    camera: CameraRealism,
    /// Scene illuminance, lux (the sun's, or the reference sun's).
    illuminance_lux: f64,
    /// Per pixel relative illumination (empty: no vignetting).
    vignette: Vec<f32>,
    /// Per pixel metering weight (centre-weighted), normalised to sum 1.
    metering: Vec<f32>,
    to_linear: Vec<f32>,
    from_linear: Vec<f32>,
    ae: Option<AeState>,
    codec: Option<Box<dyn FrameCodec>>,
    acc: Vec<f32>,
    buf: Vec<f32>,
}

impl std::fmt::Debug for Imager {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        f.debug_struct("Imager")
            .field("camera", &self.camera)
            .field("illuminance_lux", &self.illuminance_lux)
            .field("ae", &self.ae)
            .field("codec", &self.codec.as_ref().map(|c| c.describe()))
            .finish()
    }
}

/// Entries of the tone-curve tables.
const LUT: usize = 4096;
/// Largest renderer brightness the linearisation table covers.
const LUT_MAX_V: f32 = 320.0;

impl Imager {
    /// An imager for `renderer` (built with the lighting's clouds, if any)
    /// with the camera effects of `camera` under `lighting`'s sun.
    pub fn new(
        renderer: Arc<Renderer>,
        camera: CameraRealism,
        lighting: &LightingRealism,
    ) -> Imager {
        let (w, h) = (renderer.width(), renderer.height());
        let elevation = lighting
            .sun
            .map_or(REFERENCE_SUN_ELEVATION_DEG, |s| s.position().1);
        let illuminance_lux = clear_sky_illuminance_lux(elevation).max(1.0);
        let mut vignette = Vec::new();
        if let Some(v) = camera.vignetting {
            // cos^n of the off-axis angle, n from the corner's value.
            let corner_cos = renderer
                .pixel_ray(0, 0)
                .into_iter()
                .chain(renderer.pixel_ray(w - 1, h - 1))
                .map(|r| r[2])
                .fold(1.0f32, f32::min)
                .clamp(1e-3, 1.0);
            let n = if corner_cos < 1.0 {
                v.corner.ln() / (corner_cos as f64).ln()
            } else {
                0.0
            };
            vignette = (0..w * h)
                .map(|i| {
                    renderer
                        .pixel_ray(i % w, i / w)
                        .map_or(0.0, |r| (r[2].max(1e-3) as f64).powf(n) as f32)
                })
                .collect();
        }
        // Centre-weighted metering: a Gaussian of a third of the width.
        let s = w.max(h) as f32 / 3.0;
        let (cx, cy) = ((w as f32 - 1.0) * 0.5, (h as f32 - 1.0) * 0.5);
        let mut metering: Vec<f32> = (0..w * h)
            .map(|i| {
                let (dx, dy) = ((i % w) as f32 - cx, (i / w) as f32 - cy);
                (-(dx * dx + dy * dy) / (2.0 * s * s)).exp()
            })
            .collect();
        let total: f32 = metering.iter().sum();
        metering.iter_mut().for_each(|m| *m /= total.max(1e-9));
        let g = camera.photometry.display_gamma;
        let to_linear = (0..=LUT)
            .map(|i| ((i as f64 / LUT as f64) * LUT_MAX_V as f64 / 255.0).powf(g) as f32)
            .collect();
        // Indexed by sqrt(x), where the curve is nearly linear.
        let from_linear = (0..=LUT)
            .map(|i| {
                let s = i as f64 / LUT as f64;
                (255.0 * (s * s).powf(1.0 / g)) as f32
            })
            .collect();
        let codec = camera.compression.as_ref().map(codec_for);
        Imager {
            renderer,
            camera,
            illuminance_lux,
            vignette,
            metering,
            to_linear,
            from_linear,
            ae: None,
            codec,
            acc: Vec::new(),
            buf: Vec::new(),
        }
    }

    /// The renderer.
    pub fn renderer(&self) -> &Arc<Renderer> {
        &self.renderer
    }

    /// The camera effects.
    pub fn camera(&self) -> &CameraRealism {
        &self.camera
    }

    /// The scene illuminance the photometry uses, lux.
    pub fn illuminance_lux(&self) -> f64 {
        self.illuminance_lux
    }

    /// A description of the codec (None without compression).
    pub fn codec_description(&self) -> Option<String> {
        self.codec.as_ref().map(|c| c.describe())
    }

    /// Exposure time at base gain that brings a white (reflectance 1)
    /// surface lit by `lux` to full scale, seconds.
    pub fn saturating_exposure_s(&self, lux: f64) -> f64 {
        let p = &self.camera.photometry;
        p.saturation_lux_s * 4.0 * p.f_number * p.f_number / (p.lens_transmission * lux.max(1e-3))
    }

    /// The current auto-exposure (time, gain), None before the first frame
    /// or without auto-exposure.
    pub fn exposure_setting(&self) -> Option<(f64, f64)> {
        let ae = self.camera.auto_exposure?;
        let s = self.ae?;
        Some(program(&ae, s.product_s))
    }

    /// True when every camera effect is off and the world is static:
    /// captures are the renderer's plain frames (a world with moving cars
    /// or water is rendered at each frame's scene time).
    fn plain(&self) -> bool {
        let c = &self.camera;
        c.blur.is_none()
            && c.rolling_shutter.is_none()
            && c.auto_exposure.is_none()
            && c.vignetting.is_none()
            && c.noise.is_none()
            && self.renderer.clouds().is_none()
            && self.renderer.world().is_static()
    }

    /// Captures the frame whose centre row is exposed around `t_s` (the
    /// caller's clock, also the scene time), with the camera's true pose
    /// given by `pose_at` at any time near it; `noise_seed` seeds the
    /// frame's sensor noise (None: no noise at all).
    pub fn capture(
        &mut self,
        t_s: f64,
        pose_at: &dyn Fn(f64) -> Isometry3<f64>,
        noise_seed: Option<u64>,
    ) -> Result<Exposure, VideoError> {
        let world_from_cam = pose_at(t_s);
        let renderer = self.renderer.clone();
        let (w, h) = (renderer.width(), renderer.height());
        if self.plain() {
            let mut img = GrayImage::new(w as u32, h as u32);
            renderer.render_into(&world_from_cam, noise_seed, &mut img);
            return self.finish(img, t_s, world_from_cam, 0.0, 1.0, 0.0, Vec::new(), 1);
        }
        let cam = self.camera.clone();
        // Exposure time and gain for this frame (the auto-exposure's
        // state from earlier frames: it lags).
        let t_sat = self.saturating_exposure_s(self.illuminance_lux);
        let (exposure_s, gain) = match &cam.auto_exposure {
            Some(ae) => {
                let state = match self.ae {
                    Some(s) => s,
                    None => {
                        // A camera that has been running: metered on this very view.
                        let mean = self.metered_scene_mean(&world_from_cam, t_s);
                        let product = t_sat * ae.target / mean.max(1e-4);
                        let s = AeState {
                            product_s: product
                                .clamp(ae.min_exposure_s, ae.max_exposure_s * ae.max_gain),
                            last_t: t_s,
                        };
                        self.ae = Some(s);
                        s
                    }
                };
                program(ae, state.product_s)
            }
            None => (cam.photometry.fixed_exposure_s, 1.0),
        };
        let readout = cam.rolling_shutter.map_or(0.0, |r| r.readout_s);
        let line = if h > 1 { readout / (h - 1) as f64 } else { 0.0 };
        let row_time = |y: usize| t_s + (y as f64 - (h as f64 - 1.0) * 0.5) * line;
        // Sub-exposure samples.
        let samples = match &cam.blur {
            Some(b) if exposure_s > 0.0 => {
                let motion = self.image_motion_px(pose_at, t_s, exposure_s);
                ((motion / b.max_px_per_sample).ceil() as usize).clamp(1, b.max_samples)
            }
            _ => 1,
        };
        let blur_on = cam.blur.is_some() && exposure_s > 0.0;
        let knots_rows = if readout > 0.0 {
            knot_rows(h)
        } else {
            Vec::new()
        };
        let photometric = cam.auto_exposure.is_some()
            || cam.vignetting.is_some()
            || cam.noise.is_some()
            || samples > 1;
        let n = w * h;
        self.acc.clear();
        self.acc.resize(n, 0.0);
        let mut row_poses: Vec<Isometry3<f64>> = Vec::new();
        for k in 0..samples {
            // Stratified over the exposure, relative to each row's mid-exposure.
            let offset = if blur_on {
                ((k as f64 + 0.5) / samples as f64 - 0.5) * exposure_s
            } else {
                0.0
            };
            row_poses.clear();
            if readout > 0.0 {
                let knots: Vec<RowKnot> = knots_rows
                    .iter()
                    .map(|&row| {
                        let t = row_time(row) + offset;
                        RowKnot {
                            row,
                            time_s: t,
                            world_from_cam: pose_at(t),
                        }
                    })
                    .collect();
                row_poses
                    .extend((0..h).map(|y| interpolate_knots(&knots, y).unwrap_or(world_from_cam)));
            } else {
                row_poses.push(pose_at(t_s + offset));
            }
            let scene = SceneState {
                time_s: t_s + offset,
            };
            let mut buf = std::mem::take(&mut self.buf);
            // The row-pose count is 1 or h by construction.
            let _ = renderer.render_scene(&row_poses, &scene, &mut buf);
            if photometric {
                for (a, &v) in self.acc.iter_mut().zip(&buf) {
                    *a += lookup(&self.to_linear, v * (LUT as f32 / LUT_MAX_V));
                }
            } else {
                self.acc.copy_from_slice(&buf);
            }
            self.buf = buf;
        }
        let mut img = GrayImage::new(w as u32, h as u32);
        let sigma = renderer.params().noise_sigma;
        if !photometric {
            // Display-referred as the renderer gives it: the ideal noise.
            let out: &mut [u8] = &mut img;
            for (i, (o, &v)) in out.iter_mut().zip(&self.acc).enumerate() {
                let noise = match noise_seed {
                    Some(seed) if sigma > 0.0 => sigma * gaussian(seed, i as u64),
                    _ => 0.0,
                };
                *o = round_u8(v + noise);
            }
        } else {
            let inv_samples = 1.0 / samples as f32;
            // Linear signal relative to full scale, before gain.
            let scale = match &cam.auto_exposure {
                Some(_) => (exposure_s / t_sat) as f32,
                None => 1.0,
            };
            let g = gain as f32;
            let (fw, read) = match &cam.noise {
                Some(s) => (s.pixel_full_well_e() as f32, s.pixel_read_noise_e() as f32),
                None => (0.0, 0.0),
            };
            let mut metered = 0.0f64;
            let out: &mut [u8] = &mut img;
            for (i, o) in out.iter_mut().enumerate().take(n) {
                let v = if self.vignette.is_empty() {
                    1.0
                } else {
                    self.vignette[i]
                };
                let pre = self.acc[i] * inv_samples * scale * v;
                let clean = (pre * g).min(1.0);
                metered += (clean * self.metering[i]) as f64;
                let x = match (noise_seed, &cam.noise) {
                    (Some(seed), Some(_)) => {
                        // Electrons, shot noise (Gaussian approximation of
                        // the Poisson count) and read noise; the well and
                        // the converter clip.
                        let e = (pre * fw).max(0.0);
                        let e = e
                            + e.sqrt() * gaussian(seed, i as u64)
                            + read * gaussian(seed ^ 0x5EAD_0015E, i as u64);
                        (e.clamp(0.0, fw) / fw * g).min(1.0)
                    }
                    _ => clean.max(0.0),
                };
                let y = lookup(&self.from_linear, x.max(0.0).sqrt() * LUT as f32);
                let noise = match (noise_seed, &cam.noise) {
                    (Some(seed), None) if sigma > 0.0 => sigma * gaussian(seed, i as u64),
                    _ => 0.0,
                };
                *o = round_u8(y + noise);
            }
            if let (Some(ae), Some(state)) = (&cam.auto_exposure, self.ae.as_mut()) {
                let dt = (t_s - state.last_t).max(0.0);
                let alpha = if ae.tau_s > 0.0 {
                    1.0 - (-dt / ae.tau_s).exp()
                } else {
                    1.0
                };
                let wanted = state.product_s * ae.target / metered.max(1e-4);
                let product = state.product_s * (wanted / state.product_s).powf(alpha);
                state.product_s = product.clamp(ae.min_exposure_s, ae.max_exposure_s * ae.max_gain);
                state.last_t = t_s;
            }
        }
        let knots = knots_rows
            .iter()
            .map(|&row| {
                let t = row_time(row);
                RowKnot {
                    row,
                    time_s: t,
                    world_from_cam: pose_at(t),
                }
            })
            .collect();
        let exposure_reported = if blur_on || cam.auto_exposure.is_some() {
            exposure_s
        } else {
            0.0
        };
        self.finish(
            img,
            t_s,
            world_from_cam,
            exposure_reported,
            gain,
            readout,
            knots,
            samples,
        )
    }

    #[allow(clippy::too_many_arguments)]
    fn finish(
        &mut self,
        img: GrayImage,
        t_s: f64,
        world_from_cam: Isometry3<f64>,
        exposure_s: f64,
        gain: f64,
        readout_s: f64,
        row_knots: Vec<RowKnot>,
        blur_samples: usize,
    ) -> Result<Exposure, VideoError> {
        let (image, encoded, encoded_kind) = match self.codec.as_mut() {
            Some(c) => {
                let (bytes, decoded) = c.transcode(&img)?;
                (decoded, Some(bytes), Some(c.kind()))
            }
            None => (img, None, None),
        };
        Ok(Exposure {
            image,
            encoded,
            encoded_kind,
            time_s: t_s,
            world_from_cam,
            exposure_s,
            gain,
            readout_s,
            row_knots,
            blur_samples,
        })
    }

    /// Centre-weighted mean of the linear scene brightness (at full-scale
    /// white) seen from `pose`, for the auto-exposure's first metering.
    fn metered_scene_mean(&mut self, pose: &Isometry3<f64>, t_s: f64) -> f64 {
        let mut buf = std::mem::take(&mut self.buf);
        let _ = self.renderer.render_scene(
            std::slice::from_ref(pose),
            &SceneState { time_s: t_s },
            &mut buf,
        );
        let t_scale = (LUT as f32) / LUT_MAX_V;
        let mean: f64 = buf
            .iter()
            .enumerate()
            .map(|(i, &v)| {
                let vig = self.vignette.get(i).copied().unwrap_or(1.0);
                (lookup(&self.to_linear, v * t_scale) * vig * self.metering[i]) as f64
            })
            .sum();
        self.buf = buf;
        mean
    }

    /// How far the image moves during an exposure of `exposure_s` centred
    /// on `t_s`, pixels: rotation through the focal length plus translation
    /// over a conservative nearest depth (half the height above ground, at
    /// least 2 m), summed over four sub-intervals.
    fn image_motion_px(
        &self,
        pose_at: &dyn Fn(f64) -> Isometry3<f64>,
        t_s: f64,
        exposure_s: f64,
    ) -> f64 {
        let cam = self.renderer.camera();
        let f = cam.fx.max(cam.fy);
        let mut total = 0.0;
        let mut prev = pose_at(t_s - 0.5 * exposure_s);
        for k in 1..=4 {
            let next = pose_at(t_s + (k as f64 / 4.0 - 0.5) * exposure_s);
            let angle = prev.rotation.angle_to(&next.rotation);
            let shift = (next.translation.vector - prev.translation.vector).norm();
            let depth = (-0.5 * next.translation.vector.z).max(2.0);
            total += f * (angle + shift / depth);
            prev = next;
        }
        total
    }
}

/// The exposure program: time first (up to the longest), then gain.
fn program(ae: &crate::realism::AutoExposure, product_s: f64) -> (f64, f64) {
    let t = product_s.clamp(ae.min_exposure_s, ae.max_exposure_s);
    let g = (product_s / t).clamp(1.0, ae.max_gain);
    (t, g)
}

/// Linear interpolation in a table at fractional index `x` (clamped).
#[inline(always)]
fn lookup(table: &[f32], x: f32) -> f32 {
    let last = (table.len() - 1) as f32;
    let x = if x > 0.0 { x.min(last) } else { 0.0 };
    let i = (x as usize).min(table.len() - 2);
    let f = x - i as f32;
    table[i] + (table[i + 1] - table[i]) * f
}
