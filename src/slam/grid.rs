//! A grid index of keypoints over the undistorted image, for search by
//! projection: which keypoints lie within a radius of a predicted position.
//! Flat storage (cell offsets + indices), built once per frame.

use crate::camera::Camera;
use crate::features::KeyPoint;
use nalgebra::Point2;

/// Columns of the grid.
pub const GRID_COLS: usize = 64;
/// Rows of the grid.
pub const GRID_ROWS: usize = 48;

/// The undistorted image bounds of a camera: where undistorted keypoints can lie.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct Bounds {
    /// Smallest x.
    pub min_x: f64,
    /// Largest x.
    pub max_x: f64,
    /// Smallest y.
    pub min_y: f64,
    /// Largest y.
    pub max_y: f64,
}

impl Bounds {
    /// The bounding box of the undistorted image border.
    pub fn of(camera: &Camera) -> Bounds {
        let (w, h) = (camera.width as f64 - 1.0, camera.height as f64 - 1.0);
        let mut b = Bounds {
            min_x: f64::INFINITY,
            max_x: f64::NEG_INFINITY,
            min_y: f64::INFINITY,
            max_y: f64::NEG_INFINITY,
        };
        let n = 16;
        for i in 0..=n {
            let t = i as f64 / n as f64;
            for p in [
                Point2::new(t * w, 0.0),
                Point2::new(t * w, h),
                Point2::new(0.0, t * h),
                Point2::new(w, t * h),
            ] {
                let u = camera.undistort_pixel(p);
                b.min_x = b.min_x.min(u.x);
                b.max_x = b.max_x.max(u.x);
                b.min_y = b.min_y.min(u.y);
                b.max_y = b.max_y.max(u.y);
            }
        }
        b
    }

    /// True when a point lies inside.
    #[inline]
    pub fn contains(&self, x: f64, y: f64) -> bool {
        x >= self.min_x && x <= self.max_x && y >= self.min_y && y <= self.max_y
    }
}

/// Keypoint indices bucketed by cell of the undistorted image.
#[derive(Debug, Clone, Default)]
pub struct FeatureGrid {
    bounds: Option<Bounds>,
    inv_cell_w: f64,
    inv_cell_h: f64,
    /// `cell_start[c]..cell_start[c+1]` indexes `entries` for cell `c`.
    cell_start: Vec<u32>,
    /// The keypoints in cell order, with what the search tests (read in
    /// sequence rather than gathered from the keypoint list).
    entries: Vec<Entry>,
}

/// A keypoint as the grid holds it.
#[derive(Debug, Clone, Copy, Default)]
struct Entry {
    x: f32,
    y: f32,
    octave: i32,
    index: u32,
}

impl FeatureGrid {
    /// Index `keypoints` (their undistorted positions) within `bounds`.
    pub fn new(keypoints: &[KeyPoint], bounds: Bounds) -> Self {
        let inv_cell_w = GRID_COLS as f64 / (bounds.max_x - bounds.min_x).max(1e-9);
        let inv_cell_h = GRID_ROWS as f64 / (bounds.max_y - bounds.min_y).max(1e-9);
        let mut grid = FeatureGrid {
            bounds: Some(bounds),
            inv_cell_w,
            inv_cell_h,
            cell_start: vec![0; GRID_COLS * GRID_ROWS + 1],
            entries: Vec::new(),
        };
        let cells: Vec<Option<usize>> = keypoints
            .iter()
            .map(|k| {
                grid.cell_of(k.ux as f64, k.uy as f64)
                    .map(|(c, r)| r * GRID_COLS + c)
            })
            .collect();
        for c in cells.iter().flatten() {
            grid.cell_start[c + 1] += 1;
        }
        for i in 0..GRID_COLS * GRID_ROWS {
            grid.cell_start[i + 1] += grid.cell_start[i];
        }
        let mut fill = grid.cell_start.clone();
        grid.entries = vec![Entry::default(); grid.cell_start[GRID_COLS * GRID_ROWS] as usize];
        for (i, c) in cells.iter().enumerate() {
            if let Some(c) = c {
                let k = &keypoints[i];
                grid.entries[fill[*c] as usize] = Entry {
                    x: k.ux,
                    y: k.uy,
                    octave: k.octave as i32,
                    index: i as u32,
                };
                fill[*c] += 1;
            }
        }
        grid
    }

    #[inline]
    fn cell_of(&self, x: f64, y: f64) -> Option<(usize, usize)> {
        let b = self.bounds?;
        let cx = ((x - b.min_x) * self.inv_cell_w).floor();
        let cy = ((y - b.min_y) * self.inv_cell_h).floor();
        if cx < 0.0 || cy < 0.0 || cx >= GRID_COLS as f64 || cy >= GRID_ROWS as f64 {
            return None;
        }
        Some((cx as usize, cy as usize))
    }

    /// Fill `out` with the keypoints within `r` pixels (square window, then
    /// the exact circle) of `(x, y)` whose octave is in `min_level..=max_level`.
    /// `keypoints` are the ones the grid was built from (indices past their
    /// end are skipped).
    #[allow(clippy::too_many_arguments)]
    pub fn features_in_area(
        &self,
        keypoints: &[KeyPoint],
        x: f64,
        y: f64,
        r: f64,
        min_level: i32,
        max_level: i32,
        out: &mut Vec<usize>,
    ) {
        out.clear();
        let Some(b) = self.bounds else {
            return;
        };
        // Cell range of the square window. `as usize` truncates towards
        // zero and saturates negatives (and NaN) at 0, which is the floor
        // clamped at 0 for the low ends; a high end below 0 means the window
        // misses the grid.
        let (hx, hy) = (
            (x + r - b.min_x) * self.inv_cell_w,
            (y + r - b.min_y) * self.inv_cell_h,
        );
        if !(hx >= 0.0 && hy >= 0.0) {
            return;
        }
        let c0 = ((x - r - b.min_x) * self.inv_cell_w) as usize;
        let r0 = ((y - r - b.min_y) * self.inv_cell_h) as usize;
        let c1 = (hx as usize).min(GRID_COLS - 1);
        let r1 = (hy as usize).min(GRID_ROWS - 1);
        if c0 > c1 || r0 > r1 {
            return;
        }
        let r2 = (r * r) as f32;
        let (xf, yf) = (x as f32, y as f32);
        let n = keypoints.len();
        for row in r0..=r1 {
            let start = self.cell_start[row * GRID_COLS + c0] as usize;
            let end = self.cell_start[row * GRID_COLS + c1 + 1] as usize;
            for e in &self.entries[start..end] {
                if e.octave < min_level || e.octave > max_level {
                    continue;
                }
                let (dx, dy) = (e.x - xf, e.y - yf);
                if dx * dx + dy * dy <= r2 && (e.index as usize) < n {
                    out.push(e.index as usize);
                }
            }
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn finds_exactly_the_points_in_the_circle() {
        let kps: Vec<KeyPoint> = (0..2000)
            .map(|i| {
                let x = ((i * 7919) % 640) as f32 + 0.25;
                let y = ((i * 104_729) % 480) as f32 + 0.5;
                KeyPoint {
                    x,
                    y,
                    ux: x,
                    uy: y,
                    octave: (i % 8) as u8,
                    ..Default::default()
                }
            })
            .collect();
        let b = Bounds {
            min_x: 0.0,
            max_x: 640.0,
            min_y: 0.0,
            max_y: 480.0,
        };
        let g = FeatureGrid::new(&kps, b);
        let mut out = Vec::new();
        for &(x, y, r, lo, hi) in &[
            (100.0, 100.0, 30.0, 0, 7),
            (0.0, 0.0, 50.0, 2, 3),
            (639.0, 479.0, 80.0, 0, 0),
        ] {
            g.features_in_area(&kps, x, y, r, lo, hi, &mut out);
            let mut want: Vec<usize> = (0..kps.len())
                .filter(|&i| {
                    let k = &kps[i];
                    let d2 = (k.ux as f64 - x).powi(2) + (k.uy as f64 - y).powi(2);
                    d2 <= r * r && (k.octave as i32) >= lo && (k.octave as i32) <= hi
                })
                .collect();
            out.sort_unstable();
            want.sort_unstable();
            assert_eq!(out, want);
            assert!(!want.is_empty());
        }
    }
}
