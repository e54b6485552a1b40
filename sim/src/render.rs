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

use std::sync::Arc;

use image::GrayImage;
use nalgebra::{Isometry3, Point2};

use crate::camera::{Params as CameraParams, SimCamera};
use crate::texture::{fast_log2, mix64, round_u8};
use crate::world::{Face, World};

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

/// A tile's pixel range and the cone bounding its rays (camera frame).
#[derive(Debug, Clone, Copy)]
struct Tile {
    x0: usize,
    x1: usize,
    y0: usize,
    y1: usize,
    axis: [f32; 3],
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
                    cos_half: half.cos() as f32,
                    sin_half: half.sin() as f32,
                });
            }
        }
        let boxes = world
            .boxes
            .iter()
            .map(|b| {
                let c = (b.min + b.max) * 0.5;
                let r = (b.max - b.min).norm() * 0.5;
                BoxF {
                    min: [b.min.x as f32, b.min.y as f32, b.min.z as f32],
                    max: [b.max.x as f32, b.max.y as f32, b.max.z as f32],
                    centre: [c.x as f32, c.y as f32, c.z as f32],
                    radius: r as f32 * 1.0001 + 1e-3,
                }
            })
            .collect();
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
        }
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
        let r64 = world_from_cam.rotation.to_rotation_matrix();
        let m = r64.matrix();
        let r: [[f32; 3]; 3] = [
            [m[(0, 0)] as f32, m[(0, 1)] as f32, m[(0, 2)] as f32],
            [m[(1, 0)] as f32, m[(1, 1)] as f32, m[(1, 2)] as f32],
            [m[(2, 0)] as f32, m[(2, 1)] as f32, m[(2, 2)] as f32],
        ];
        let t = world_from_cam.translation.vector;
        let o = [t.x as f32, t.y as f32, t.z as f32];
        if !(o.iter().all(|v| v.is_finite()) && r.iter().flatten().all(|v| v.is_finite())) {
            img.fill(0);
            return;
        }
        // Boxes relative to the camera.
        let views: Vec<BoxView> = self
            .boxes
            .iter()
            .enumerate()
            .map(|(i, b)| {
                let rel_min = [b.min[0] - o[0], b.min[1] - o[1], b.min[2] - o[2]];
                let rel_max = [b.max[0] - o[0], b.max[1] - o[1], b.max[2] - o[2]];
                let v = [b.centre[0] - o[0], b.centre[1] - o[1], b.centre[2] - o[2]];
                let dist = (v[0] * v[0] + v[1] * v[1] + v[2] * v[2]).sqrt();
                let inside = dist <= b.radius;
                let sin_b = if inside { 1.0 } else { b.radius / dist };
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
            .collect();
        // Candidate boxes of every tile, flat, with each tile's range.
        let mut candidates: Vec<BoxView> = Vec::with_capacity(views.len() * 4);
        let mut ranges: Vec<(usize, usize)> = Vec::with_capacity(self.tiles.len());
        let aa = self.params.edge_antialias;
        let mut ids: Vec<u32> = if aa {
            vec![INVALID_ID; self.width * self.height]
        } else {
            Vec::new()
        };
        let buf: &mut [u8] = img;
        let noise_sigma = self.params.noise_sigma;
        let noise = |i: usize| match noise_seed {
            Some(seed) if noise_sigma > 0.0 => noise_sigma * gaussian(seed, i as u64),
            _ => 0.0,
        };
        for tile in &self.tiles {
            let axis = rot(&r, tile.axis);
            let start = candidates.len();
            for b in &views {
                let hit = b.inside || {
                    let c = axis[0] * b.dir[0] + axis[1] * b.dir[1] + axis[2] * b.dir[2];
                    // angle(axis, dir) <= half + beta  <=>  cos >= cos(half + beta) (if half + beta < pi).
                    let sin_sum = tile.sin_half * b.cos_b + tile.cos_half * b.sin_b;
                    let cos_sum = tile.cos_half * b.cos_b - tile.sin_half * b.sin_b;
                    sin_sum < 0.0 || c >= cos_sum
                };
                if hit {
                    candidates.push(*b);
                }
            }
            ranges.push((start, candidates.len()));
            let cands = &candidates[start..];
            for y in tile.y0..tile.y1 {
                let row = y * self.width;
                for x in tile.x0..tile.x1 {
                    let i = row + x;
                    let ray = self.rays[i];
                    if ray[2] == 0.0 && ray[0] == 0.0 && ray[1] == 0.0 {
                        buf[i] = 0;
                        continue;
                    }
                    let d = rot(&r, [ray[0], ray[1], ray[2]]);
                    let (value, id) = self.shade(o, d, ray[3], cands);
                    if aa {
                        ids[i] = id;
                    }
                    buf[i] = round_u8(value + noise(i));
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
        for y in 0..h {
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
                let Some(&(a, b)) = ranges.get((y / ts) * tiles_x + x / ts) else {
                    continue;
                };
                let cands = &candidates[a..b];
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
                    let d = rot(&r, [c[0] / n, c[1] / n, c[2] / n]);
                    // A sub-pixel is half the pixel across: half the footprint.
                    sum += self.shade(o, d, ray[3] - 1.0, cands).0;
                }
                buf[i] = round_u8(sum / offsets.len() as f32 + noise(i));
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
        let value = if let Some((index, axis, positive)) = hit_box {
            let face = Face::from_axis(axis, positive);
            id = BOX_ID0 + 6 * index + face.index() as u32;
            let cos = d[axis].abs().max(1e-3);
            let lod_m = fast_log2(t) + log_omega - fast_log2(cos) + p.lod_bias;
            let hit = [o[0] + d[0] * t, o[1] + d[1] * t, o[2] + d[2] * t];
            match self.world.boxes.get(index as usize) {
                Some(b) => self.world.box_value(b, face, hit, lod_m),
                None => 0.0,
            }
        } else if ground {
            let cos = d[2].max(1e-3);
            let lod_m = fast_log2(t) + log_omega - fast_log2(cos) + p.lod_bias;
            self.world
                .ground_value(o[0] + d[0] * t, o[1] + d[1] * t, lod_m)
        } else {
            // Sky (or ground beyond the far distance, lost in haze).
            let up = (-d[2]).max(0.0);
            let v = if d[2] > 0.0 {
                p.haze_value
            } else {
                p.sky_horizon + (p.sky_zenith - p.sky_horizon) * up
            };
            return (v, SKY_ID);
        };
        let keep = (1.0 - t * self.inv_haze_range).max(0.0);
        (value * keep + p.haze_value * (1.0 - keep), id)
    }
}

/// An approximately standard-normal number from (seed, index): the
/// centred sum of four 16-bit uniforms (Irwin-Hall), scaled to unit variance.
#[inline(always)]
fn gaussian(seed: u64, index: u64) -> f32 {
    let h = mix64(seed ^ index.wrapping_mul(0x9e37_79b9_7f4a_7c15));
    let s = (h & 0xffff) + ((h >> 16) & 0xffff) + ((h >> 32) & 0xffff) + (h >> 48);
    // Sum of four U(0,1) has mean 2 and variance 1/3.
    ((s as f32) * (1.0 / 65535.0) - 2.0) * 1.732_050_8
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::world::WorldParams;
    use nalgebra::{Point3, Translation3, UnitQuaternion, Vector3};

    fn small_world() -> Arc<World> {
        Arc::new(World::generate_with(3, &WorldParams::small()).unwrap())
    }

    fn look_at(eye: Point3<f64>, target: Point3<f64>) -> Isometry3<f64> {
        let f = (target - eye).normalize();
        let right = Vector3::z().cross(&f).normalize();
        let down = f.cross(&right);
        let m = nalgebra::Matrix3::from_columns(&[right, down, f]);
        let q = UnitQuaternion::from_matrix(&m);
        Isometry3::from_parts(Translation3::from(eye.coords), q)
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
