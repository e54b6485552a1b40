//! Keypoint orientation by intensity centroid (Rosin; ORB's `IC_Angle`).
//!
//! The moments `m10 = sum u I(u, v)` and `m01 = sum v I(u, v)` are summed over
//! a disc of radius `r` around the keypoint; the angle is `atan2(m01, m10)`.
//! The disc is `{(u, v) : u^2 + v^2 <= (r + 1/2)^2}`, symmetric under swapping
//! `u` and `v`, so the measured angle turns with the image.

/// Half-widths of the disc rows: `umax[|v|]` is the largest `|u|` in row `v`.
#[derive(Debug, Clone, PartialEq)]
pub struct Disc {
    umax: Vec<i32>,
}

impl Disc {
    /// The disc of radius `r` (`patch_size / 2`).
    pub fn new(r: usize) -> Disc {
        let r2 = (r as f64 + 0.5) * (r as f64 + 0.5);
        let umax = (0..=r)
            .map(|v| (r2 - (v * v) as f64).sqrt().floor() as i32)
            .collect();
        Disc { umax }
    }

    /// Radius of the disc.
    pub fn radius(&self) -> usize {
        self.umax.len().saturating_sub(1)
    }

    /// Half-width of row `v` (`|v| <= radius`).
    pub fn half_width(&self, v: usize) -> i32 {
        self.umax.get(v).copied().unwrap_or(0)
    }

    /// Orientation in degrees, `[0, 360)`, of the patch centred on `(x, y)` of
    /// the `w`-wide image `img`. The caller keeps the disc inside the image;
    /// pixels that fall outside count as 0.
    #[inline(always)]
    pub fn angle(&self, img: &[u8], w: usize, x: usize, y: usize) -> f32 {
        let r = self.radius();
        if x < r || y < r || x + r >= w || (y + r + 1) * w > img.len() {
            return 0.0;
        }
        let mut m10: i64 = 0;
        let mut m01: i64 = 0;
        let d0 = self.umax[0] as usize;
        let centre = &img[y * w + x - d0..y * w + x + d0 + 1];
        m10 += centre
            .iter()
            .enumerate()
            .map(|(i, &p)| (i as i32 - d0 as i32) * p as i32)
            .sum::<i32>() as i64;
        for v in 1..=r {
            let d = self.umax[v] as usize;
            let plus = &img[(y + v) * w + x - d..(y + v) * w + x + d + 1];
            let minus = &img[(y - v) * w + x - d..(y - v) * w + x + d + 1];
            let mut sum_u = 0i32;
            let mut sum_v = 0i32;
            for (i, (&a, &b)) in plus.iter().zip(minus).enumerate() {
                let u = i as i32 - d as i32;
                sum_u += u * (a as i32 + b as i32);
                sum_v += a as i32 - b as i32;
            }
            m10 += sum_u as i64;
            m01 += v as i64 * sum_v as i64;
        }
        let a = (m01 as f32).atan2(m10 as f32).to_degrees();
        if a < 0.0 { a + 360.0 } else { a }
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn disc_matches_orb_slam_table() {
        let d = Disc::new(15);
        let want = [15, 15, 15, 15, 14, 14, 14, 13, 13, 12, 11, 10, 9, 8, 6, 3];
        assert_eq!(d.umax, want);
        // Symmetric under transposition.
        for v in 0..=15usize {
            for u in 0..=15i32 {
                let inside = u <= d.half_width(v);
                let inside_t = (v as i32) <= d.half_width(u as usize);
                assert_eq!(inside, inside_t, "u {u} v {v}");
            }
        }
    }

    #[test]
    fn angle_points_to_the_bright_side() {
        let w = 64;
        let d = Disc::new(15);
        for (deg, (dx, dy)) in [
            (0.0f32, (1.0f32, 0.0f32)),
            (90.0, (0.0, 1.0)),
            (225.0, (-1.0, -1.0)),
        ] {
            // Intensity ramp rising along (dx, dy).
            let img: Vec<u8> = (0..w * w)
                .map(|i| {
                    let (x, y) = ((i % w) as f32 - 32.0, (i / w) as f32 - 32.0);
                    (128.0 + 3.0 * (x * dx + y * dy)).clamp(0.0, 255.0) as u8
                })
                .collect();
            let a = d.angle(&img, w, 32, 32);
            let diff = ((a - deg + 540.0) % 360.0 - 180.0).abs();
            assert!(diff < 1.0, "want {deg} got {a}");
        }
        assert_eq!(d.angle(&[0u8; 100], 10, 5, 5), 0.0);
    }
}
