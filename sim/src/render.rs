//! The renderer: ray casting through the distorted camera into the world.
//!
//! At construction the renderer undistorts every pixel once (the camera
//! model's Newton inversion) into a unit ray in camera coordinates and its
//! angular size. Per frame it rotates the rays into the world, intersects
//! them analytically with the ground plane and the boxes, and samples the
//! mip-mapped textures at a level of detail taken from the pixel's
//! footprint on the surface (distance x angular size / cos(incidence)), so
//! the texture is filtered instead of aliasing. Boxes are culled per
//! 16x16-pixel tile against a cone that bounds the tile's rays, so a pixel
//! tests only the few boxes that can cover it.
//!
//! Pixel `(i, j)` is the ray through the distorted pixel coordinate
//! `(i, j)` (integer coordinates are pixel centres, as in OpenCV), so a
//! world point renders where [`SimCamera::project`] says.

use std::borrow::Cow;
use std::sync::Arc;

use image::GrayImage;
use nalgebra::{Isometry3, Point2};

use crate::camera::{Params as CameraParams, SimCamera};
use crate::texture::{fast_log2, mix64, round_u8};
use crate::world::{Face, SceneBox, World};

/// Every tunable number of the renderer.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct RenderParams {
    /// Standard deviation of the additive sensor noise of
    /// [`Renderer::render_noisy`], in grey levels (0 disables it).
    pub noise_sigma: f32,
    /// Added to the log2 of every footprint: > 0 blurs, < 0 sharpens (and aliases).
    pub lod_bias: f32,
    /// Haze grows linearly with distance and has taken all contrast at
    /// this distance, metres (half of it at half the distance).
    pub haze_range_m: f32,
    /// Grey level of the haze.
    pub haze_value: f32,
    /// Rays end here (beyond: haze), metres.
    pub max_distance_m: f32,
    /// Sky grey level at the horizon.
    pub sky_horizon: f32,
    /// Sky grey level at the zenith.
    pub sky_zenith: f32,
    /// Grey level seen from inside a box.
    pub inside_value: f32,
    /// Side of the square culling tiles, pixels.
    pub tile_size: usize,
    /// Re-shade pixels on geometric edges (a change of box, face, ground
    /// or sky) with sub-pixel rays (2x2, or 2 along the one axis the edge
    /// is crossed on), so silhouettes are anti-aliased.
    pub edge_antialias: bool,
}

impl Default for RenderParams {
    fn default() -> Self {
        Self {
            noise_sigma: 2.0,
            lod_bias: 0.0,
            haze_range_m: 3000.0,
            haze_value: 200.0,
            max_distance_m: 3000.0,
            sky_horizon: 215.0,
            sky_zenith: 170.0,
            inside_value: 15.0,
            tile_size: 16,
            edge_antialias: true,
        }
    }
}

/// Surface id of the sky (and of ground beyond the far distance).
const SKY_ID: u32 = 0;
/// Surface id seen from inside a box.
const INSIDE_ID: u32 = 1;
/// Surface id of the ground.
const GROUND_ID: u32 = 2;
/// Surface id of face `f` of box `b` is `BOX_ID0 + 6 b + f`.
const BOX_ID0: u32 = 3;
/// A pixel without a ray.
const INVALID_ID: u32 = u32::MAX;

/// A box in render form (single precision).
#[derive(Debug, Clone, Copy)]
struct BoxF {
    min: [f32; 3],
    max: [f32; 3],
    centre: [f32; 3],
    radius: f32,
}

impl BoxF {
    fn from_box(b: &SceneBox) -> BoxF {
        let c = (b.min + b.max) * 0.5;
        let r = (b.max - b.min).norm() * 0.5;
        BoxF {
            min: [b.min.x as f32, b.min.y as f32, b.min.z as f32],
            max: [b.max.x as f32, b.max.y as f32, b.max.z as f32],
            centre: [c.x as f32, c.y as f32, c.z as f32],
            radius: r as f32 * 1.0001 + 1e-3,
        }
    }
}

/// A tile's pixel range and the cone bounding its rays (camera frame).
#[derive(Debug, Clone, Copy)]
struct Tile {
    x0: usize,
    x1: usize,
    y0: usize,
    y1: usize,
    axis: [f32; 3],
    /// Half angle of the cone, radians.
    half: f32,
    cos_half: f32,
    sin_half: f32,
}

/// A box as seen from the current camera position.
#[derive(Debug, Clone, Copy)]
struct BoxView {
    index: u32,
    rel_min: [f32; 3],
    rel_max: [f32; 3],
    dir: [f32; 3],
    sin_b: f32,
    cos_b: f32,
    inside: bool,
}

/// Renders 8-bit grey images of a [`World`] through a [`SimCamera`].
#[derive(Debug, Clone)]
pub struct Renderer {
    world: Arc<World>,
    camera: SimCamera,
    params: RenderParams,
    width: usize,
    height: usize,
    /// Per pixel: unit ray (camera frame) and log2 of its angular size; a
    /// zero ray marks a pixel that could not be undistorted.
    rays: Vec<[f32; 4]>,
    tiles: Vec<Tile>,
    boxes: Vec<BoxF>,
    inv_haze_range: f32,
    /// Moving cloud shadows (only in [`Renderer::render_scene`]).
    clouds: Option<CloudField>,
    /// Unit vector towards the sun (NED), single precision.
    sun_f: [f32; 3],
}

#[inline(always)]
fn rot(r: &[[f32; 3]; 3], v: [f32; 3]) -> [f32; 3] {
    [
        r[0][0] * v[0] + r[0][1] * v[1] + r[0][2] * v[2],
        r[1][0] * v[0] + r[1][1] * v[1] + r[1][2] * v[2],
        r[2][0] * v[0] + r[2][1] * v[1] + r[2][2] * v[2],
    ]
}

impl Renderer {
    /// Prepares per-pixel rays and tiles for `camera` (an invalid camera
    /// renders black; pixels that cannot be undistorted render black).
    pub fn new(world: Arc<World>, camera: SimCamera, params: RenderParams) -> Renderer {
        let valid = camera.validate().is_ok();
        let (width, height) = (camera.width as usize, camera.height as usize);
        let cam_params = CameraParams::default();
        let mut dirs: Vec<Option<[f64; 3]>> = Vec::with_capacity(width * height);
        for v in 0..height {
            for u in 0..width {
                let ray = if valid {
                    camera
                        .pixel_to_ray(Point2::new(u as f64, v as f64), &cam_params)
                        .ok()
                } else {
                    None
                };
                dirs.push(ray.map(|r| [r.x, r.y, r.z]));
            }
        }
        let angle = |a: [f64; 3], b: [f64; 3]| {
            let d = [a[0] - b[0], a[1] - b[1], a[2] - b[2]];
            (d[0] * d[0] + d[1] * d[1] + d[2] * d[2]).sqrt()
        };
        let at = |u: isize, v: isize| -> Option<[f64; 3]> {
            if u < 0 || v < 0 || u >= width as isize || v >= height as isize {
                None
            } else {
                dirs[v as usize * width + u as usize]
            }
        };
        let mut rays = vec![[0.0f32; 4]; width * height];
        for v in 0..height as isize {
            for u in 0..width as isize {
                let Some(c) = at(u, v) else { continue };
                // Angular pixel size from neighbouring rays (one-sided at edges).
                let du = match (at(u - 1, v), at(u + 1, v)) {
                    (Some(a), Some(b)) => angle(a, b) * 0.5,
                    (Some(a), None) => angle(a, c),
                    (None, Some(b)) => angle(b, c),
                    (None, None) => 1.0 / camera.fx,
                };
                let dv = match (at(u, v - 1), at(u, v + 1)) {
                    (Some(a), Some(b)) => angle(a, b) * 0.5,
                    (Some(a), None) => angle(a, c),
                    (None, Some(b)) => angle(b, c),
                    (None, None) => 1.0 / camera.fy,
                };
                let omega = (du * dv).sqrt().max(1e-9) as f32;
                rays[v as usize * width + u as usize] =
                    [c[0] as f32, c[1] as f32, c[2] as f32, omega.log2()];
            }
        }
        let ts = params.tile_size.max(1);
        let mut tiles = Vec::new();
        for y0 in (0..height).step_by(ts) {
            for x0 in (0..width).step_by(ts) {
                let (x1, y1) = ((x0 + ts).min(width), (y0 + ts).min(height));
                let mut axis = [0.0f64; 3];
                for y in y0..y1 {
                    for x in x0..x1 {
                        if let Some(d) = dirs[y * width + x] {
                            axis = [axis[0] + d[0], axis[1] + d[1], axis[2] + d[2]];
                        }
                    }
                }
                let n = (axis[0] * axis[0] + axis[1] * axis[1] + axis[2] * axis[2]).sqrt();
                let axis = if n > 0.0 {
                    [axis[0] / n, axis[1] / n, axis[2] / n]
                } else {
                    [0.0, 0.0, 1.0]
                };
                let mut cos_min = 1.0f64;
                for y in y0..y1 {
                    for x in x0..x1 {
                        if let Some(d) = dirs[y * width + x] {
                            cos_min = cos_min.min(d[0] * axis[0] + d[1] * axis[1] + d[2] * axis[2]);
                        }
                    }
                }
                // A small margin for rounding in single precision.
                let half = cos_min.clamp(-1.0, 1.0).acos() + 1e-3;
                tiles.push(Tile {
                    x0,
                    x1,
                    y0,
                    y1,
                    axis: [axis[0] as f32, axis[1] as f32, axis[2] as f32],
                    half: half as f32,
                    cos_half: half.cos() as f32,
                    sin_half: half.sin() as f32,
                });
            }
        }
        let boxes = world.boxes.iter().map(BoxF::from_box).collect();
        let sun = world.sun_dir;
        let sun_f = [sun.x as f32, sun.y as f32, sun.z as f32];
        Renderer {
            world,
            camera,
            params,
            width,
            height,
            rays,
            tiles,
            boxes,
            inv_haze_range: 1.0 / params.haze_range_m.max(1e-3),
            clouds: None,
            sun_f,
        }
    }

    /// The same renderer with moving cloud shadows over the scene (seen by
    /// [`Renderer::render_scene`]; the plain renders stay without them).
    pub fn with_clouds(mut self, clouds: CloudShadows) -> Renderer {
        self.clouds = Some(CloudField::new(clouds));
        self
    }

    /// The cloud shadows, if any.
    pub fn clouds(&self) -> Option<&CloudShadows> {
        self.clouds.as_ref().map(|c| &c.params)
    }

    /// Image width, pixels.
    pub fn width(&self) -> usize {
        self.width
    }

    /// Image height, pixels.
    pub fn height(&self) -> usize {
        self.height
    }

    /// Unit ray (camera frame) through pixel `(x, y)`, `None` outside the
    /// image or where the camera model could not be inverted.
    pub fn pixel_ray(&self, x: usize, y: usize) -> Option<[f32; 3]> {
        if x >= self.width || y >= self.height {
            return None;
        }
        let r = self.rays[y * self.width + x];
        (r[0] != 0.0 || r[1] != 0.0 || r[2] != 0.0).then_some([r[0], r[1], r[2]])
    }

    /// The camera model.
    pub fn camera(&self) -> &SimCamera {
        &self.camera
    }

    /// The world.
    pub fn world(&self) -> &Arc<World> {
        &self.world
    }

    /// The parameters.
    pub fn params(&self) -> &RenderParams {
        &self.params
    }

    /// Renders a noise-free image from `world_from_cam`.
    pub fn render(&self, world_from_cam: &Isometry3<f64>) -> GrayImage {
        let mut img = GrayImage::new(self.width as u32, self.height as u32);
        self.render_into(world_from_cam, None, &mut img);
        img
    }

    /// Renders with additive Gaussian sensor noise of
    /// [`RenderParams::noise_sigma`], deterministic for `seed`.
    pub fn render_noisy(&self, world_from_cam: &Isometry3<f64>, seed: u64) -> GrayImage {
        let mut img = GrayImage::new(self.width as u32, self.height as u32);
        self.render_into(world_from_cam, Some(seed), &mut img);
        img
    }

    /// Renders into `img` (reallocated if its size differs); with
    /// `noise_seed`, adds the seeded sensor noise.
    pub fn render_into(
        &self,
        world_from_cam: &Isometry3<f64>,
        noise_seed: Option<u64>,
        img: &mut GrayImage,
    ) {
        if img.width() as usize != self.width || img.height() as usize != self.height {
            *img = GrayImage::new(self.width as u32, self.height as u32);
        }
        let Some(pose) = PoseF::new(world_from_cam) else {
            img.fill(0);
            return;
        };
        let ctx = FrameCtx {
            boxes_f: Cow::Borrowed(&self.boxes),
            boxes: Cow::Borrowed(&self.world.boxes),
            clouds: None,
            time_s: 0.0,
        };
        let buf: &mut [u8] = img;
        let noise_sigma = self.params.noise_sigma;
        // A pixel without a ray arrives as NaN, which rounds to 0.
        self.render_core(&[pose], &ctx, |i, value| {
            let noise = match noise_seed {
                Some(seed) if noise_sigma > 0.0 => noise_sigma * gaussian(seed, i as u64),
                _ => 0.0,
            };
            buf[i] = round_u8(value + noise);
        });
    }

    /// Renders the scene's brightness (the renderer's grey scale, before
    /// any sensor: no noise, no rounding, no clipping) at scene time
    /// `scene.time_s` into `out` (row-major, resized to the image).
    ///
    /// `row_poses` holds either one `world_from_cam` for the whole frame
    /// (a global shutter) or one per image row (a rolling shutter: row `y`
    /// is seen from `row_poses[y]`). Moving objects stand where they are
    /// at `scene.time_s`; cloud shadows (see [`Renderer::with_clouds`])
    /// have drifted with their wind to that time. Pixels without a ray,
    /// and every pixel of a frame with a non-finite pose, are 0.
    pub fn render_scene(
        &self,
        row_poses: &[Isometry3<f64>],
        scene: &SceneState,
        out: &mut Vec<f32>,
    ) -> Result<(), RenderError> {
        if !(row_poses.len() == 1 || row_poses.len() == self.height) {
            return Err(RenderError::RowPoses {
                found: row_poses.len(),
                height: self.height,
            });
        }
        out.clear();
        out.resize(self.width * self.height, 0.0);
        let Some(poses) = row_poses.iter().map(PoseF::new).collect::<Option<Vec<_>>>() else {
            return Ok(());
        };
        let time = scene.time_s as f32;
        let boxes = self.world.boxes_at(scene.time_s);
        let boxes_f = match &boxes {
            Cow::Borrowed(_) => Cow::Borrowed(&self.boxes[..]),
            Cow::Owned(b) => Cow::Owned(b.iter().map(BoxF::from_box).collect()),
        };
        let ctx = FrameCtx {
            boxes_f,
            boxes,
            clouds: self.clouds.as_ref().map(|c| (c, c.offset_at(scene.time_s))),
            time_s: time,
        };
        self.render_core(&poses, &ctx, |i, value| {
            out[i] = if value.is_nan() { 0.0 } else { value };
        });
        Ok(())
    }

    /// The ray-casting core: calls `sink(pixel_index, brightness)` for
    /// every pixel (NaN for a pixel without a ray), and again for pixels on
    /// geometric edges with their anti-aliased brightness (the last call
    /// wins). `poses` has one pose, or one per row.
    fn render_core<S: FnMut(usize, f32)>(&self, poses: &[PoseF], ctx: &FrameCtx, mut sink: S) {
        let per_row = poses.len() > 1;
        let pose_of_row = |y: usize| if per_row { &poses[y] } else { &poses[0] };
        let boxes_f = &ctx.boxes_f[..];
        // Candidate boxes of every tile, flat, with each tile's range; the
        // views are relative to the band's reference pose.
        let mut candidates: Vec<BoxView> = Vec::with_capacity(boxes_f.len() * 4);
        let mut ranges: Vec<(usize, usize)> = Vec::with_capacity(self.tiles.len());
        let mut band_ref: Vec<usize> = Vec::new();
        let aa = self.params.edge_antialias;
        let mut ids: Vec<u32> = if aa {
            vec![INVALID_ID; self.width * self.height]
        } else {
            Vec::new()
        };
        let mut views: Vec<BoxView> = Vec::new();
        let mut band_y0 = usize::MAX;
        // Extra cone angle (radians) for the rotation of a band's rows away
        // from its reference row; zero with one pose.
        let mut extra_angle = 0.0f32;
        let mut ref_index = 0usize;
        let mut shifted: Vec<BoxView> = Vec::new();
        for tile in &self.tiles {
            if tile.y0 != band_y0 {
                band_y0 = tile.y0;
                if per_row {
                    ref_index = (tile.y0 + tile.y1 - 1) / 2;
                    let reference = &poses[ref_index];
                    let (mut angle, mut shift) = (0.0f32, 0.0f32);
                    for p in &poses[tile.y0..tile.y1] {
                        angle = angle.max(reference.angle_to(p));
                        shift = shift.max(dist3(reference.o, p.o));
                    }
                    extra_angle = angle;
                    views = box_views(boxes_f, reference.o, shift);
                } else if views.is_empty() && !boxes_f.is_empty() {
                    views = box_views(boxes_f, poses[0].o, 0.0);
                }
            }
            band_ref.push(ref_index);
            let reference = &poses[ref_index];
            let axis = rot(&reference.r, tile.axis);
            let (sin_half, cos_half) = if extra_angle > 0.0 {
                let half = tile.half + extra_angle;
                (half.sin(), half.cos())
            } else {
                (tile.sin_half, tile.cos_half)
            };
            let start = candidates.len();
            for b in &views {
                let hit = b.inside || {
                    let c = axis[0] * b.dir[0] + axis[1] * b.dir[1] + axis[2] * b.dir[2];
                    // angle(axis, dir) <= half + beta  <=>  cos >= cos(half + beta) (if half + beta < pi).
                    let sin_sum = sin_half * b.cos_b + cos_half * b.sin_b;
                    let cos_sum = cos_half * b.cos_b - sin_half * b.sin_b;
                    sin_sum < 0.0 || c >= cos_sum
                };
                if hit {
                    candidates.push(*b);
                }
            }
            ranges.push((start, candidates.len()));
            for y in tile.y0..tile.y1 {
                let pose = pose_of_row(y);
                let cands: &[BoxView] = if per_row && pose.o != reference.o {
                    shift_views(&candidates[start..], boxes_f, pose.o, &mut shifted);
                    &shifted
                } else {
                    &candidates[start..]
                };
                let row = y * self.width;
                for x in tile.x0..tile.x1 {
                    let i = row + x;
                    let ray = self.rays[i];
                    if ray[2] == 0.0 && ray[0] == 0.0 && ray[1] == 0.0 {
                        sink(i, f32::NAN);
                        continue;
                    }
                    let d = rot(&pose.r, [ray[0], ray[1], ray[2]]);
                    let (value, id) = self.shade(pose.o, d, ray[3], cands, ctx);
                    if aa {
                        ids[i] = id;
                    }
                    sink(i, value);
                }
            }
        }
        if !aa {
            return;
        }
        // Edge anti-aliasing: pixels whose surface differs from a
        // 4-neighbour's are re-shaded as the mean of 2x2 sub-pixel rays.
        let (w, h) = (self.width, self.height);
        let ts = self.params.tile_size.max(1);
        let tiles_x = w.div_ceil(ts);
        let mut shifted_key = usize::MAX;
        for y in 0..h {
            let pose = pose_of_row(y);
            for x in 0..w {
                let i = y * w + x;
                let id = ids[i];
                if id == INVALID_ID {
                    continue;
                }
                let differs = |j: usize| ids[j] != id && ids[j] != INVALID_ID;
                let across_x = (x + 1 < w && differs(i + 1)) || (x > 0 && differs(i - 1));
                let across_y = (y + 1 < h && differs(i + w)) || (y > 0 && differs(i - w));
                // An edge crossed along one axis only needs sub-samples along
                // that axis (a 2x2 grid would sample the same two columns or rows).
                const GRID: [(f32, f32); 4] =
                    [(-0.25, -0.25), (0.25, -0.25), (-0.25, 0.25), (0.25, 0.25)];
                const ALONG_X: [(f32, f32); 2] = [(-0.25, 0.0), (0.25, 0.0)];
                const ALONG_Y: [(f32, f32); 2] = [(0.0, -0.25), (0.0, 0.25)];
                let offsets: &[(f32, f32)] = match (across_x, across_y) {
                    (true, true) => &GRID,
                    (true, false) => &ALONG_X,
                    (false, true) => &ALONG_Y,
                    (false, false) => continue,
                };
                let tile_index = (y / ts) * tiles_x + x / ts;
                let Some(&(a, b)) = ranges.get(tile_index) else {
                    continue;
                };
                let reference = &poses[band_ref.get(tile_index).copied().unwrap_or(0)];
                let cands: &[BoxView] = if per_row && pose.o != reference.o {
                    let key = y * self.tiles.len() + tile_index;
                    if key != shifted_key {
                        shift_views(&candidates[a..b], boxes_f, pose.o, &mut shifted);
                        shifted_key = key;
                    }
                    &shifted
                } else {
                    &candidates[a..b]
                };
                // Ray steps of one pixel along x and y (central differences, one-sided at borders).
                let step = |j0: usize, j1: usize, span: f32| {
                    let (p, q) = (self.rays[j0], self.rays[j1]);
                    [
                        (q[0] - p[0]) / span,
                        (q[1] - p[1]) / span,
                        (q[2] - p[2]) / span,
                    ]
                };
                let (xl, xr) = (
                    if x > 0 { i - 1 } else { i },
                    if x + 1 < w { i + 1 } else { i },
                );
                let (yu, yd) = (
                    if y > 0 { i - w } else { i },
                    if y + 1 < h { i + w } else { i },
                );
                let du = step(xl, xr, (xr - xl) as f32);
                let dv = step(yu, yd, ((yd - yu) / w) as f32);
                let ray = self.rays[i];
                let mut sum = 0.0;
                for &(ox, oy) in offsets {
                    let c = [
                        ray[0] + du[0] * ox + dv[0] * oy,
                        ray[1] + du[1] * ox + dv[1] * oy,
                        ray[2] + du[2] * ox + dv[2] * oy,
                    ];
                    let n = (c[0] * c[0] + c[1] * c[1] + c[2] * c[2]).sqrt();
                    let d = rot(&pose.r, [c[0] / n, c[1] / n, c[2] / n]);
                    // A sub-pixel is half the pixel across: half the footprint.
                    sum += self.shade(pose.o, d, ray[3] - 1.0, cands, ctx).0;
                }
                sink(i, sum / offsets.len() as f32);
            }
        }
    }

    /// Brightness seen along world direction `d` from `o`, and the id of
    /// the surface seen ([`SKY_ID`], [`INSIDE_ID`], [`GROUND_ID`], or
    /// `BOX_ID0 + 6 * box + face`).
    #[inline(always)]
    fn shade(
        &self,
        o: [f32; 3],
        d: [f32; 3],
        log_omega: f32,
        candidates: &[BoxView],
        ctx: &FrameCtx,
    ) -> (f32, u32) {
        let p = &self.params;
        let mut t_best = p.max_distance_m;
        let mut ground = false;
        if d[2] > 1e-7 && o[2] < 0.0 {
            let t = -o[2] / d[2];
            if t < t_best {
                t_best = t;
                ground = true;
            }
        }
        let mut hit_box: Option<(u32, usize, bool)> = None;
        if !candidates.is_empty() {
            let inv = [1.0 / d[0], 1.0 / d[1], 1.0 / d[2]];
            for b in candidates {
                let mut t0 = f32::NEG_INFINITY;
                let mut t1 = t_best;
                let mut axis = 0usize;
                #[allow(clippy::needless_range_loop)] // `a` also names the hit axis
                for a in 0..3 {
                    let ta = b.rel_min[a] * inv[a];
                    let tb = b.rel_max[a] * inv[a];
                    let (lo, hi) = if ta < tb { (ta, tb) } else { (tb, ta) };
                    if lo > t0 {
                        t0 = lo;
                        axis = a;
                    }
                    if hi < t1 {
                        t1 = hi;
                    }
                }
                if t0 <= t1 {
                    if t0 > 0.0 {
                        t_best = t0;
                        hit_box = Some((b.index, axis, d[axis] > 0.0));
                        ground = false;
                    } else if t1 > 0.0 {
                        // The camera is inside this box.
                        return (p.inside_value, INSIDE_ID);
                    }
                }
            }
        }
        let t = t_best;
        let mut id = GROUND_ID;
        let hit = [o[0] + d[0] * t, o[1] + d[1] * t, o[2] + d[2] * t];
        let value = if let Some((index, axis, positive)) = hit_box {
            let face = Face::from_axis(axis, positive);
            id = BOX_ID0 + 6 * index + face.index() as u32;
            let cos = d[axis].abs().max(1e-3);
            let lod_m = fast_log2(t) + log_omega - fast_log2(cos) + p.lod_bias;
            match ctx.boxes.get(index as usize) {
                Some(b) => self.world.box_value(b, face, hit, lod_m),
                None => 0.0,
            }
        } else if ground {
            let cos = d[2].max(1e-3);
            let lod_m = fast_log2(t) + log_omega - fast_log2(cos) + p.lod_bias;
            if !self.world.water.is_empty() && self.world.water_at(hit[0], hit[1]) {
                self.water_value(hit, d, ctx)
            } else {
                self.world.ground_value(hit[0], hit[1], lod_m)
            }
        } else {
            // Sky (or ground beyond the far distance, lost in haze).
            return (self.sky_value(d), SKY_ID);
        };
        let value = match ctx.clouds {
            Some((clouds, offset)) => {
                value * clouds.light_factor(hit, &self.sun_f, offset, self.world.params.ambient)
            }
            None => value,
        };
        let keep = (1.0 - t * self.inv_haze_range).max(0.0);
        (value * keep + p.haze_value * (1.0 - keep), id)
    }

    /// Sky brightness along world direction `d` (haze below the horizon).
    #[inline(always)]
    fn sky_value(&self, d: [f32; 3]) -> f32 {
        let p = &self.params;
        let up = (-d[2]).max(0.0);
        if d[2] > 0.0 {
            p.haze_value
        } else {
            p.sky_horizon + (p.sky_zenith - p.sky_horizon) * up
        }
    }

    /// Water at `hit` seen along `d`: a rippled mirror (Fresnel-weighted
    /// reflection of the boxes and the sky, with sun glitter) over a dark,
    /// slowly changing body. The ripples move with scene time, so nothing
    /// on the surface stays put.
    fn water_value(&self, hit: [f32; 3], d: [f32; 3], ctx: &FrameCtx) -> f32 {
        let n = crate::world::water_normal(hit[0], hit[1], ctx.time_s);
        let dn = d[0] * n[0] + d[1] * n[1] + d[2] * n[2];
        // Reflect about the (upward, -z) normal.
        let r = [
            d[0] - 2.0 * dn * n[0],
            d[1] - 2.0 * dn * n[1],
            d[2] - 2.0 * dn * n[2],
        ];
        let cos_i = (-dn).clamp(0.0, 1.0);
        // Schlick's approximation for water (n = 1.33): R0 = 0.02.
        let fresnel = 0.02 + 0.98 * (1.0 - cos_i).powi(5);
        let origin = [hit[0], hit[1], hit[2] - 0.01];
        let reflected = if r[2] < 0.0 {
            match self.trace_boxes(origin, r, &ctx.boxes_f) {
                Some((index, face, point, _)) => ctx
                    .boxes
                    .get(index)
                    .map_or(0.0, |b| self.world.box_value(b, face, point, 2.0)),
                None => {
                    let s = &self.sun_f;
                    let glint = (r[0] * s[0] + r[1] * s[1] + r[2] * s[2]).max(0.0);
                    self.sky_value(r) + 2500.0 * glint.powi(256)
                }
            }
        } else {
            self.world.water_body_value(hit[0], hit[1], ctx.time_s)
        };
        let body = self.world.water_body_value(hit[0], hit[1], ctx.time_s);
        fresnel * reflected + (1.0 - fresnel) * body
    }

    /// The first box (index, face, hit point, distance) along a ray, over
    /// every box (for secondary rays, which the tile culling does not cover).
    fn trace_boxes(
        &self,
        o: [f32; 3],
        d: [f32; 3],
        boxes: &[BoxF],
    ) -> Option<(usize, Face, [f32; 3], f32)> {
        let inv = [1.0 / d[0], 1.0 / d[1], 1.0 / d[2]];
        let mut best: Option<(usize, Face, f32)> = None;
        let mut t_best = self.params.max_distance_m;
        for (index, b) in boxes.iter().enumerate() {
            let mut t0 = 0.0f32;
            let mut t1 = t_best;
            let mut axis = 0usize;
            let mut ok = true;
            for a in 0..3 {
                let ta = (b.min[a] - o[a]) * inv[a];
                let tb = (b.max[a] - o[a]) * inv[a];
                let (lo, hi) = if ta < tb { (ta, tb) } else { (tb, ta) };
                if lo > t0 {
                    t0 = lo;
                    axis = a;
                }
                t1 = t1.min(hi);
                if t0 > t1 {
                    ok = false;
                    break;
                }
            }
            if ok && t0 > 0.0 && t0 < t_best {
                t_best = t0;
                best = Some((index, Face::from_axis(axis, d[axis] > 0.0), t0));
            }
        }
        best.map(|(i, f, t)| (i, f, [o[0] + d[0] * t, o[1] + d[1] * t, o[2] + d[2] * t], t))
    }
}

/// Errors of the renderer's checked entry points.
#[derive(Debug, Clone, PartialEq, thiserror::Error)]
pub enum RenderError {
    /// Row poses must be one for the frame or one per image row.
    #[error("{found} row poses for an image of {height} rows: give 1 or {height}")]
    RowPoses {
        /// Poses given.
        found: usize,
        /// Image rows.
        height: usize,
    },
}

/// The time-dependent state of the scene for one exposure sample.
#[derive(Debug, Clone, Copy, PartialEq, Default)]
pub struct SceneState {
    /// Scene time, seconds: moving objects, water ripples and cloud
    /// shadows are where they are at this time.
    pub time_s: f64,
}

/// A camera pose in render form (single precision).
#[derive(Debug, Clone, Copy, PartialEq)]
struct PoseF {
    r: [[f32; 3]; 3],
    o: [f32; 3],
}

impl PoseF {
    /// None when the pose is not finite.
    fn new(world_from_cam: &Isometry3<f64>) -> Option<PoseF> {
        let r64 = world_from_cam.rotation.to_rotation_matrix();
        let m = r64.matrix();
        let r: [[f32; 3]; 3] = [
            [m[(0, 0)] as f32, m[(0, 1)] as f32, m[(0, 2)] as f32],
            [m[(1, 0)] as f32, m[(1, 1)] as f32, m[(1, 2)] as f32],
            [m[(2, 0)] as f32, m[(2, 1)] as f32, m[(2, 2)] as f32],
        ];
        let t = world_from_cam.translation.vector;
        let o = [t.x as f32, t.y as f32, t.z as f32];
        (o.iter().all(|v| v.is_finite()) && r.iter().flatten().all(|v| v.is_finite()))
            .then_some(PoseF { r, o })
    }

    /// Rotation angle between two poses, radians (from the trace of
    /// `R_a^T R_b`), with a small margin for single-precision rounding.
    fn angle_to(&self, other: &PoseF) -> f32 {
        let mut trace = 0.0f32;
        for i in 0..3 {
            for k in 0..3 {
                trace += self.r[k][i] * other.r[k][i];
            }
        }
        ((trace - 1.0) * 0.5).clamp(-1.0, 1.0).acos() + 1e-4
    }
}

fn dist3(a: [f32; 3], b: [f32; 3]) -> f32 {
    let d = [a[0] - b[0], a[1] - b[1], a[2] - b[2]];
    (d[0] * d[0] + d[1] * d[1] + d[2] * d[2]).sqrt()
}

/// The per-frame scene the core shades: boxes where they are now, and the
/// cloud shadows with their drift.
struct FrameCtx<'a> {
    boxes_f: Cow<'a, [BoxF]>,
    boxes: Cow<'a, [SceneBox]>,
    clouds: Option<(&'a CloudField, [f32; 2])>,
    time_s: f32,
}

/// Every box as seen from camera position `o`; `extra_radius` widens each
/// box's bounding sphere (the camera moves that far over a band of rows).
fn box_views(boxes: &[BoxF], o: [f32; 3], extra_radius: f32) -> Vec<BoxView> {
    boxes
        .iter()
        .enumerate()
        .map(|(i, b)| {
            let rel_min = [b.min[0] - o[0], b.min[1] - o[1], b.min[2] - o[2]];
            let rel_max = [b.max[0] - o[0], b.max[1] - o[1], b.max[2] - o[2]];
            let v = [b.centre[0] - o[0], b.centre[1] - o[1], b.centre[2] - o[2]];
            let dist = (v[0] * v[0] + v[1] * v[1] + v[2] * v[2]).sqrt();
            let radius = b.radius + extra_radius;
            let inside = dist <= radius;
            let sin_b = if inside { 1.0 } else { radius / dist };
            let cos_b = (1.0 - sin_b * sin_b).max(0.0).sqrt();
            let inv = if dist > 0.0 { 1.0 / dist } else { 0.0 };
            BoxView {
                index: i as u32,
                rel_min,
                rel_max,
                dir: [v[0] * inv, v[1] * inv, v[2] * inv],
                sin_b,
                cos_b,
                inside,
            }
        })
        .collect()
}

/// `views` re-expressed relative to camera position `o` into `out`.
fn shift_views(views: &[BoxView], boxes: &[BoxF], o: [f32; 3], out: &mut Vec<BoxView>) {
    out.clear();
    out.extend(views.iter().map(|v| {
        let b = &boxes[v.index as usize];
        BoxView {
            rel_min: [b.min[0] - o[0], b.min[1] - o[1], b.min[2] - o[2]],
            rel_max: [b.max[0] - o[0], b.max[1] - o[1], b.max[2] - o[2]],
            ..*v
        }
    }));
}

/// Moving cloud shadows: a cloud layer at an altitude, its cover a
/// thresholded smooth noise field (soft-edged, so shadows have a penumbra),
/// drifting with the wind at that altitude. A point on the ground or on a
/// box is shadowed by the cloud its ray towards the sun crosses; in shadow
/// it loses `opacity` of the direct (non-ambient) light.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct CloudShadows {
    /// Share of the sky covered, 0..1.
    pub cover: f32,
    /// Typical cloud size, metres (the noise field's base wavelength).
    pub scale_m: f32,
    /// Width of a shadow's soft edge, metres.
    pub edge_m: f32,
    /// Share of the direct sunlight a cloud stops, 0..1.
    pub opacity: f32,
    /// Cloud base altitude above the ground, metres.
    pub altitude_m: f32,
    /// Drift velocity of the clouds (north, east), m/s.
    pub velocity_m_s: [f32; 2],
    /// Seed of the cloud field.
    pub seed: u64,
}

/// The precomputed cloud cover of [`CloudShadows`]: a wrapping grid of
/// shadow amounts (0 clear, 1 full cloud) over a square of the cloud layer.
#[derive(Debug, Clone)]
pub(crate) struct CloudField {
    params: CloudShadows,
    size: usize,
    inv_texel: f32,
    cover: Vec<f32>,
}

impl CloudField {
    /// Grid texels across the cloud layer.
    const SIZE: usize = 512;

    pub(crate) fn new(params: CloudShadows) -> CloudField {
        let size = Self::SIZE;
        // The layer spans 16 cloud scales, so the field wraps far outside any view.
        let extent = params.scale_m.max(1.0) * 16.0;
        let mut canvas = crate::texture::Canvas::new(size, 0.0);
        canvas.add_fbm(16, 4, 1.0, 0.5, params.seed ^ 0xC10D);
        let mut values: Vec<f32> = canvas.data().to_vec();
        // The threshold leaving `cover` of the field above it.
        let mut sorted = values.clone();
        sorted.sort_by(f32::total_cmp);
        let cover = params.cover.clamp(0.0, 1.0);
        let k = (((1.0 - cover) * sorted.len() as f32) as usize).min(sorted.len() - 1);
        let threshold = sorted[k];
        // The field's slope in value per metre sets the soft edge's value width.
        let (lo, hi) = (sorted[sorted.len() / 10], sorted[sorted.len() * 9 / 10]);
        let per_metre = (hi - lo) / params.scale_m.max(1.0);
        let half = (0.5 * params.edge_m.max(0.01) * per_metre).max(1e-6);
        for v in &mut values {
            let s = ((*v - threshold) / half * 0.5 + 0.5).clamp(0.0, 1.0);
            *v = if cover <= 0.0 {
                0.0
            } else {
                s * s * (3.0 - 2.0 * s)
            };
        }
        CloudField {
            params,
            size,
            inv_texel: size as f32 / extent,
            cover: values,
        }
    }

    /// The cloud layer's displacement at scene time `t`, metres.
    fn offset_at(&self, t: f64) -> [f32; 2] {
        let v = self.params.velocity_m_s;
        [(v[0] as f64 * t) as f32, (v[1] as f64 * t) as f32]
    }

    /// Cloud cover (0..1) over layer point (x, y), bilinear, wrapping.
    fn cover_at(&self, x: f32, y: f32) -> f32 {
        let n = self.size as i32;
        let (u, v) = (x * self.inv_texel, y * self.inv_texel);
        let (x0, fx) = crate::texture::split_floor(u);
        let (y0, fy) = crate::texture::split_floor(v);
        let at = |i: i32, j: i32| {
            self.cover[(j.rem_euclid(n) as usize) * self.size + i.rem_euclid(n) as usize]
        };
        let top = at(x0, y0) + (at(x0 + 1, y0) - at(x0, y0)) * fx;
        let bottom = at(x0, y0 + 1) + (at(x0 + 1, y0 + 1) - at(x0, y0 + 1)) * fx;
        top + (bottom - top) * fy
    }

    /// Light factor (1 in the sun, down to `1 - (1 - ambient) opacity`
    /// under a full cloud) at world point `p` for sun direction `sun`
    /// (towards the sun, NED) with the layer displaced by `offset`.
    #[inline(always)]
    fn light_factor(&self, p: [f32; 3], sun: &[f32; 3], offset: [f32; 2], ambient: f32) -> f32 {
        // Follow the ray towards the sun up to the cloud base (z = -altitude).
        let lambda = (-self.params.altitude_m - p[2]) / sun[2].min(-1e-3);
        let x = p[0] + sun[0] * lambda - offset[0];
        let y = p[1] + sun[1] * lambda - offset[1];
        let c = self.cover_at(x, y);
        1.0 - (1.0 - ambient) * self.params.opacity * c
    }
}

/// An approximately standard-normal number from (seed, index): the
/// centred sum of four 16-bit uniforms (Irwin-Hall), scaled to unit variance.
#[inline(always)]
pub(crate) fn gaussian(seed: u64, index: u64) -> f32 {
    let h = mix64(seed ^ index.wrapping_mul(0x9e37_79b9_7f4a_7c15));
    let s = (h & 0xffff) + ((h >> 16) & 0xffff) + ((h >> 32) & 0xffff) + (h >> 48);
    // Sum of four U(0,1) has mean 2 and variance 1/3.
    ((s as f32) * (1.0 / 65535.0) - 2.0) * 1.732_050_8
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::paths::look_at;
    use crate::world::WorldParams;
    use nalgebra::{Point3, Vector3};

    fn small_world() -> Arc<World> {
        Arc::new(World::generate_with(3, &WorldParams::small()).unwrap())
    }

    #[test]
    fn pixel_rays_hit_points_that_project_back_onto_the_pixel() {
        let world = small_world();
        let cam = SimCamera::default();
        let r = Renderer::new(world.clone(), cam, RenderParams::default());
        let pose = look_at(
            Point3::new(-60.0, -40.0, -35.0),
            Point3::new(10.0, 5.0, 0.0),
        );
        let mut worst: f64 = 0.0;
        let mut n = 0;
        for v in (0..480).step_by(37) {
            for u in (0..640).step_by(41) {
                let ray = r.rays[v * 640 + u];
                let d_cam = Vector3::new(ray[0] as f64, ray[1] as f64, ray[2] as f64);
                let d_world = pose.rotation * d_cam;
                let Some(hit) =
                    world.ray_cast(&Point3::from(pose.translation.vector), &d_world, 1e4)
                else {
                    continue;
                };
                let p_cam = pose.inverse_transform_point(&hit.p_world);
                let px = cam.project(&p_cam.coords).unwrap();
                worst = worst.max((px - Point2::new(u as f64, v as f64)).norm());
                n += 1;
            }
        }
        assert!(n > 100);
        assert!(worst < 0.01, "worst {worst} px");
    }

    #[test]
    fn rendering_is_deterministic_and_noise_is_seeded() {
        let world = small_world();
        let cam = SimCamera {
            width: 160,
            height: 120,
            fx: 115.0,
            fy: 115.0,
            cx: 79.5,
            cy: 59.5,
            ..SimCamera::default()
        };
        let r = Renderer::new(world, cam, RenderParams::default());
        let pose = look_at(Point3::new(-30.0, 20.0, -25.0), Point3::new(0.0, 0.0, 0.0));
        let a = r.render(&pose);
        assert_eq!(a, r.render(&pose));
        let n1 = r.render_noisy(&pose, 9);
        assert_eq!(n1, r.render_noisy(&pose, 9));
        assert_ne!(n1, r.render_noisy(&pose, 10));
        // Noise statistics: mean ~0, sigma ~ noise_sigma (clipping aside).
        let diffs: Vec<f64> = a
            .as_raw()
            .iter()
            .zip(n1.as_raw())
            .filter(|(x, _)| **x > 10 && **x < 245)
            .map(|(x, y)| *y as f64 - *x as f64)
            .collect();
        let mean = diffs.iter().sum::<f64>() / diffs.len() as f64;
        let sd =
            (diffs.iter().map(|d| (d - mean).powi(2)).sum::<f64>() / diffs.len() as f64).sqrt();
        assert!(mean.abs() < 0.1, "mean {mean}");
        // Rounding adds 1/12 of variance.
        let expected = (4.0f64 + 1.0 / 12.0).sqrt();
        assert!((sd - expected).abs() < 0.15, "sd {sd}");
        // A textured view is not flat.
        let mean_a = a.as_raw().iter().map(|&v| v as f64).sum::<f64>() / a.as_raw().len() as f64;
        let var_a = a
            .as_raw()
            .iter()
            .map(|&v| (v as f64 - mean_a).powi(2))
            .sum::<f64>()
            / a.as_raw().len() as f64;
        assert!(var_a.sqrt() > 15.0, "contrast {}", var_a.sqrt());
    }

    #[test]
    fn edge_antialiasing_approaches_a_supersampled_reference() {
        let world = small_world();
        let cam = SimCamera {
            width: 160,
            height: 120,
            fx: 115.0,
            fy: 115.0,
            cx: 79.5,
            cy: 59.5,
            ..SimCamera::default()
        };
        // 4x4 supersampled reference: same normalized camera at 4x resolution.
        let hi = SimCamera {
            width: 640,
            height: 480,
            fx: 460.0,
            fy: 460.0,
            cx: 319.5,
            cy: 239.5,
            ..cam
        };
        let params = RenderParams {
            noise_sigma: 0.0,
            ..RenderParams::default()
        };
        let on = Renderer::new(world.clone(), cam, params);
        let off = Renderer::new(
            world.clone(),
            cam,
            RenderParams {
                edge_antialias: false,
                ..params
            },
        );
        let reference = Renderer::new(
            world,
            hi,
            RenderParams {
                edge_antialias: false,
                ..params
            },
        );
        let (mut err_on, mut err_off, mut n) = (0.0, 0.0, 0);
        for eye in [
            Point3::new(-70.0, -30.0, -12.0),
            Point3::new(60.0, 50.0, -20.0),
        ] {
            let pose = look_at(eye, Point3::new(0.0, 0.0, -10.0));
            let (a, b, r) = (on.render(&pose), off.render(&pose), reference.render(&pose));
            for y in 0..120u32 {
                for x in 0..160u32 {
                    // Edge pixels are where the two renders differ.
                    let (va, vb) = (a.get_pixel(x, y).0[0] as f64, b.get_pixel(x, y).0[0] as f64);
                    if va == vb {
                        continue;
                    }
                    let mut sum = 0.0;
                    for j in 0..4 {
                        for i in 0..4 {
                            sum += r.get_pixel(4 * x + i, 4 * y + j).0[0] as f64;
                        }
                    }
                    let vr = sum / 16.0;
                    err_on += (va - vr).abs();
                    err_off += (vb - vr).abs();
                    n += 1;
                }
            }
        }
        eprintln!(
            "edge pixels {n}: mean error vs 4x4 supersampled {:.2} with AA, {:.2} without",
            err_on / n as f64,
            err_off / n as f64
        );
        assert!(n > 200, "only {n} edge pixels");
        let (err_on, err_off) = (err_on / n as f64, err_off / n as f64);
        assert!(
            err_on < 0.7 * err_off,
            "edge error with AA {err_on:.2}, without {err_off:.2} over {n} pixels"
        );
    }

    #[test]
    fn tile_culling_matches_brute_force() {
        // Render with tiny tiles vs a single huge tile: culling must not change pixels.
        let world = small_world();
        let cam = SimCamera {
            width: 200,
            height: 150,
            fx: 140.0,
            fy: 140.0,
            cx: 99.5,
            cy: 74.5,
            ..SimCamera::default()
        };
        let tiled = Renderer::new(
            world.clone(),
            cam,
            RenderParams {
                tile_size: 8,
                ..RenderParams::default()
            },
        );
        let whole = Renderer::new(
            world,
            cam,
            RenderParams {
                tile_size: 10_000,
                ..RenderParams::default()
            },
        );
        for eye in [
            Point3::new(-50.0, -50.0, -15.0),
            Point3::new(40.0, -70.0, -40.0),
            Point3::new(0.0, 0.0, -5.0),
        ] {
            let pose = look_at(eye, Point3::new(5.0, 0.0, -3.0));
            assert_eq!(tiled.render(&pose), whole.render(&pose));
        }
    }
}
