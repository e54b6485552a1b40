//! The newest pairs that agree, when a georeference's pairs as a whole do
//! not (see [`Georeference::fit`]): a GNSS bias that drifted over a long
//! flight.

use nalgebra::Vector3;

use super::{
    AlignParams, AlignQuality, GeoAlignment, Georeference, Pair, fit_pairs, inliers_needed,
    residual, rms_max, spread,
};
use crate::geo::GeoError;
use crate::geometry::Sim3;

impl Georeference {
    /// When the pairs do not agree as a whole, a fit of the newest pairs
    /// that agree among themselves: the newest seven eighths, six eighths,
    /// ... the most that agree (None when none do). A GNSS bias drifts
    /// (metres in height over minutes), so a long flight's pairs disagree
    /// with each other while each stretch agrees; the vehicle flies by its
    /// GNSS as it reads now, so the newest pairs are the ones its targets
    /// must agree with. Each stretch is fitted afresh while its motion
    /// allows; when it is too small or too straight for a whole Sim(3)
    /// (the flight to a shot, a hover), the last fit is moved by the
    /// stretch's median offset: what a GNSS bias changes is where NED
    /// sits, not the map's scale or rotation.
    pub(super) fn fit_newest(&self, previous: Option<&Sim3>, seed: u64) -> Option<GeoAlignment> {
        let mut newest_first = self.pairs.clone();
        newest_first.sort_by(|a, b| b.time.total_cmp(&a.time));
        let needed = self.params.min_pairs.max(3);
        let step = (newest_first.len() / 8).max(1);
        let mut n = newest_first.len().saturating_sub(step);
        let mut thin = false;
        while n >= needed {
            let newest = &newest_first[..n];
            let fitted = if thin {
                None
            } else {
                match fit_pairs(newest, &self.params, previous, seed) {
                    Ok(a) => Some(a),
                    Err(e) => {
                        tracing::debug!(
                            newest = n,
                            of = self.pairs.len(),
                            "geo: the newest pairs: {e}"
                        );
                        thin = !matches!(e, GeoError::TooFewInliers { .. });
                        None
                    }
                }
            };
            // A shift of the last fit keeps the mount offsets it learned.
            let fitted = fitted.or_else(|| {
                let mut a = shifted(previous?, newest, &self.params)?;
                a.mount_offset = self.last.as_ref().and_then(|l| l.mount_offset);
                Some(a)
            });
            if let Some(mut a) = fitted {
                a.quality.set_aside = self.pairs.len() - n;
                return Some(a);
            }
            n -= step;
        }
        tracing::debug!(
            pairs = self.pairs.len(),
            "geo: the pairs disagree, and so do the newest of them"
        );
        None
    }
}

/// `fit` moved by the pairs' median offset from it (per NED axis), when
/// at least `min_inlier_ratio` of them (and 3) then lie within the inlier
/// threshold; None otherwise. The quality's rotation and time offset are
/// not estimated (None), its iterations 0.
fn shifted(fit: &Sim3, pairs: &[Pair], params: &AlignParams) -> Option<GeoAlignment> {
    let offsets: Vec<Vector3<f64>> = pairs
        .iter()
        .map(|p| p.p_ned - fit.transform_point(&p.p_map))
        .collect();
    let axis = |k: usize| crate::stats::median(&offsets.iter().map(|o| o[k]).collect::<Vec<_>>());
    let delta = Vector3::new(axis(0)?, axis(1)?, axis(2)?);
    let model = Sim3 {
        translation: fit.translation + delta,
        ..*fit
    };
    let th = params.inlier_threshold_m;
    let (inliers, r): (Vec<&Pair>, Vec<f64>) = pairs
        .iter()
        .map(|p| (p, residual(&model, p)))
        .filter(|(_, r)| *r < th)
        .unzip();
    if inliers.len() < inliers_needed(params, pairs.len()).max(3) {
        return None;
    }
    let (rms_m, max_residual_m) = rms_max(&r);
    Some(GeoAlignment {
        ned_from_map: model,
        quality: AlignQuality {
            rms_m,
            max_residual_m,
            rotation_rms_deg: None,
            time_offset_s: None,
            pairs: pairs.len(),
            inliers: inliers.len(),
            iterations: 0,
            spread_m2: spread(inliers.iter().map(|p| p.p_ned)),
            set_aside: 0,
            gnss_bias_m: None,
        },
        inlier_ids: inliers.iter().map(|p| p.kf_id).collect(),
        mount_offset: None,
    })
}

#[cfg(test)]
mod tests {
    use super::*;
    use nalgebra::{Point3, UnitQuaternion};

    fn pair(kf_id: u64, fit: &Sim3, p_ned: Point3<f64>, read: Point3<f64>) -> Pair {
        Pair {
            kf_id,
            p_map: fit.inverse().transform_point(&p_ned),
            p_ned: read,
            time: kf_id as f64,
            orientations: None,
            v_ned: None,
        }
    }

    #[test]
    fn a_straight_stretch_moves_the_last_fit_by_its_bias() {
        // A straight flight then a hover, read with a GNSS bias that
        // stepped (1.5 m down, 0.3 m north) since `fit` was made, 3 of 40
        // pairs gross outliers: the fit moves by the bias, scale and
        // rotation kept, the outliers left out.
        let fit = Sim3 {
            rotation: UnitQuaternion::from_euler_angles(0.3, -0.2, 1.9),
            translation: Vector3::new(4.0, -7.0, -20.0),
            scale: 11.5,
        };
        let bias = Vector3::new(0.3, 0.0, 1.5);
        let pairs: Vec<Pair> = (0..40u64)
            .map(|k| {
                let along = (k as f64).min(30.0);
                let p = Point3::new(along, 0.5 * along, -20.0);
                let wobble = Vector3::new(0.0, ((k * 7) % 5) as f64 * 0.02, 0.0);
                let gross = if k % 13 == 5 {
                    Vector3::new(0.0, 4.0, 0.0)
                } else {
                    Vector3::zeros()
                };
                pair(k, &fit, p, p + bias + wobble + gross)
            })
            .collect();
        let a =
            shifted(&fit, &pairs, &AlignParams::default()).expect("the stretch agrees once moved");
        let moved = a.ned_from_map.translation - fit.translation;
        assert!((moved - bias).norm() < 0.06, "moved by {moved}");
        assert_eq!(
            (a.ned_from_map.scale, a.ned_from_map.rotation),
            (fit.scale, fit.rotation)
        );
        assert_eq!((a.quality.pairs, a.quality.inliers), (40, 37));
        assert!(a.quality.rms_m < 0.06, "{:?}", a.quality);
    }

    #[test]
    fn a_stretch_that_does_not_agree_with_itself_is_not_moved_onto() {
        // Thirds of the pairs 3 m apart: no single offset puts half of
        // them within the threshold.
        let fit = Sim3 {
            rotation: UnitQuaternion::identity(),
            translation: Vector3::zeros(),
            scale: 1.0,
        };
        let pairs: Vec<Pair> = (0..21u64)
            .map(|k| {
                let p = Point3::new(k as f64, 0.0, -10.0);
                let off = Vector3::new(0.0, 0.0, (k % 3) as f64 * 3.0 + 0.01 * k as f64);
                pair(k, &fit, p, p + off)
            })
            .collect();
        let a = shifted(&fit, &pairs, &AlignParams::default());
        assert!(a.is_none(), "{a:?}");
    }
}
