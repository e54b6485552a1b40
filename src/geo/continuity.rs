//! The georeference across a restart, as parts without state of their
//! own: the saved georeference of the previous run while its pairs wait
//! for the continued map's keyframes ([`Restore`]: taken, carried to
//! another home, placed onto the keyframes, reported), what each pair's
//! map side hangs from ([`Anchor`]) and how a held pair is saved, and the
//! check of the restored pairs against live ones ([`check_saved`]).
//! [`super::live::LiveGeoreference`] keeps them over a run.

use std::collections::HashMap;

use nalgebra::Isometry3;

use super::Params;
use super::align::{Pair, fit_pairs};
use super::saved::{PairKind, SAVED_FORMAT, SavedFit, SavedGeoreference, SavedPair, SavedPose};
use super::wgs84::{Geodetic, LocalFrame};

/// The keyframes of the map by id: capture time and `map ← cam`.
pub type KeyframePoses = HashMap<u64, (f64, Isometry3<f64>)>;

/// What a pair's map side hangs from.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct Anchor {
    /// A keyframe's own pair or a tracked frame's.
    pub kind: PairKind,
    /// The keyframe.
    pub kf: u64,
    /// That keyframe's capture time (names it across runs).
    pub kf_time: f64,
    /// `cam ← kf_cam`: the identity for a keyframe's own pair.
    pub cam_from_kf: Isometry3<f64>,
}

impl Anchor {
    /// A keyframe's own pair.
    pub fn keyframe(kf: u64, kf_time: f64) -> Self {
        Self {
            kind: PairKind::Keyframe,
            kf,
            kf_time,
            cam_from_kf: Isometry3::identity(),
        }
    }

    /// The anchor a saved pair names (a broken relative pose is the
    /// identity).
    pub fn of_saved(p: &SavedPair) -> Self {
        Self {
            kind: p.kind,
            kf: p.anchor_kf,
            kf_time: p.anchor_time,
            cam_from_kf: p
                .cam_from_anchor
                .to_isometry()
                .unwrap_or_else(Isometry3::identity),
        }
    }

    /// The held pair `p` as saved, hung from this anchor; None when its
    /// orientations are not known.
    pub fn saved_pair(&self, p: &Pair) -> Option<SavedPair> {
        let (_, ned_rot) = p.orientations?;
        Some(SavedPair {
            id: p.kf_id,
            kind: self.kind,
            anchor_kf: self.kf,
            anchor_time: self.kf_time,
            cam_from_anchor: SavedPose::from_isometry(&self.cam_from_kf),
            time: p.time,
            ned_from_cam: SavedPose::from_isometry(&Isometry3::from_parts(
                p.p_ned.coords.into(),
                ned_rot,
            )),
            v_ned: p.v_ned.map(Into::into),
        })
    }
}

/// Where a saved pair goes in the continued map: `(map ← cam, ned ← cam)`,
/// when its anchor keyframe is in `poses` with the saved capture time and
/// both poses are sound.
pub fn place(p: &SavedPair, poses: &KeyframePoses) -> Option<(Isometry3<f64>, Isometry3<f64>)> {
    let map_from_cam = poses
        .get(&p.anchor_kf)
        .filter(|(t, _)| *t == p.anchor_time)
        .and_then(|(_, world_from_kf)| p.map_from_cam(&world_from_kf.inverse()))?;
    Some((map_from_cam, p.ned_from_cam.to_isometry()?))
}

/// The saved georeference of the previous run, while it is restored.
#[derive(Debug, Clone)]
pub struct Restore {
    /// The home the waiting pairs are expressed in.
    pub home: Geodetic,
    /// Pairs not restored yet (their keyframes not seen yet).
    pub waiting: Vec<SavedPair>,
    /// Pairs in the file.
    pub loaded: usize,
    /// Pairs restored onto the map.
    pub restored: usize,
    /// Pairs that found no keyframe (or were refused).
    pub unmatched: usize,
    /// When the file was written, unix seconds.
    pub saved_unix: f64,
    /// The fit when the file was written.
    pub file_fit: Option<SavedFit>,
    /// Why the saved pairs were dropped, if they were.
    pub dropped: Option<String>,
    /// How far the vehicle's home is from the saved one, metres.
    pub home_moved_m: Option<f64>,
}

impl Restore {
    /// Takes a saved georeference; None (logged) for a file of another
    /// format or with an invalid home.
    pub fn from_saved(saved: SavedGeoreference) -> Option<Self> {
        if saved.format != SAVED_FORMAT {
            tracing::warn!(
                format = saved.format,
                "geo: saved georeference of another format ignored"
            );
            return None;
        }
        if !saved.home.is_valid() {
            tracing::warn!("geo: saved georeference with an invalid home ignored");
            return None;
        }
        let n = saved.pairs.len();
        tracing::info!(
            pairs = n,
            rms_m = saved.fit.map(|f| f.rms_m),
            "geo: saved georeference loaded; its pairs wait for the map"
        );
        Some(Self {
            home: saved.home,
            waiting: saved.pairs,
            loaded: n,
            restored: 0,
            unmatched: 0,
            saved_unix: saved.saved_unix,
            file_fit: saved.fit,
            dropped: None,
            home_moved_m: None,
        })
    }

    /// Carries the waiting saved pairs to `home`; returns how far it moved,
    /// metres (0 when it is the same home).
    pub fn rebase(&mut self, home: Geodetic) -> f64 {
        let from = LocalFrame::new(self.home);
        let to = LocalFrame::new(home);
        let moved = to.geodetic_to_ned(&self.home).norm();
        self.home_moved_m = Some(moved);
        if moved < 1e-3 {
            return 0.0;
        }
        self.waiting = self
            .waiting
            .iter()
            .filter_map(|p| p.rebased(&from, &to))
            .collect();
        self.home = home;
        moved
    }

    /// The waiting pairs to place now: none while it is not known whether
    /// the map was continued (`continued` None) or while the map has no
    /// keyframes; all of them once it is known to be continued; dropped
    /// (counted unmatched, the reason kept) when it was not.
    pub fn take_waiting(
        &mut self,
        continued: Option<bool>,
        map_has_keyframes: bool,
    ) -> Option<Vec<SavedPair>> {
        if self.waiting.is_empty() {
            return None;
        }
        match continued {
            Some(false) => {
                tracing::info!(
                    pairs = self.waiting.len(),
                    "geo: the saved map was not continued; its saved georeference is dropped"
                );
                self.unmatched += self.waiting.len();
                self.waiting.clear();
                self.dropped = Some("the saved map was not continued".into());
                None
            }
            Some(true) if map_has_keyframes => Some(std::mem::take(&mut self.waiting)),
            _ => None,
        }
    }

    /// The saved pairs disagreed with live ones (`why`): none wait any more.
    pub fn drop_all(&mut self, why: String) {
        self.dropped = Some(why);
        self.waiting.clear();
    }

    /// The status's `saved` object, with the check's state.
    pub fn status(&self, check: Option<&Check>) -> SavedStatus {
        SavedStatus {
            pairs_in_file: self.loaded,
            restored: self.restored,
            waiting: self.waiting.len(),
            unmatched: self.unmatched,
            saved_unix: self.saved_unix,
            fit_when_saved: self.file_fit,
            home_moved_m: self.home_moved_m,
            dropped: self.dropped.clone(),
            check: check.cloned(),
        }
    }
}

/// The saved georeference of a continued map.
#[derive(Debug, Clone, PartialEq, serde::Serialize)]
pub struct SavedStatus {
    /// Pairs in the file.
    pub pairs_in_file: usize,
    /// Restored onto the map's keyframes.
    pub restored: usize,
    /// Still waiting for their keyframes.
    pub waiting: usize,
    /// Whose keyframe the map does not have.
    pub unmatched: usize,
    /// When the file was written, Unix s.
    pub saved_unix: f64,
    /// The fit when the file was written.
    pub fit_when_saved: Option<SavedFit>,
    /// How far the home moved since, m (None: the same home).
    pub home_moved_m: Option<f64>,
    /// Why the saved pairs were dropped, if they were.
    pub dropped: Option<String>,
    /// The saved pairs checked against live ones.
    pub check: Option<Check>,
}

/// The saved pairs checked against live ones.
#[derive(Debug, Clone, PartialEq, serde::Serialize)]
#[serde(tag = "state", rename_all = "snake_case")]
pub enum Check {
    /// Not enough live pairs yet.
    Waiting {
        /// Live pairs held.
        live_pairs: usize,
        /// Live pairs needed.
        needed: usize,
    },
    /// The saved pairs alone give no fit.
    Unfitted {
        /// Why.
        reason: String,
    },
    /// The live pairs agree with the saved georeference.
    Agrees {
        /// Live pairs compared.
        live_pairs: usize,
        /// Their median residual under the saved pairs' fit, metres.
        median_residual_m: f64,
        /// The largest median that agrees, metres.
        bound_m: f64,
    },
    /// They do not: the saved pairs are dropped.
    Disagrees {
        /// Live pairs compared.
        live_pairs: usize,
        /// Their median residual under the saved pairs' fit, metres.
        median_residual_m: f64,
        /// The largest median that agrees, metres.
        bound_m: f64,
    },
}

impl Check {
    /// Why the saved pairs are dropped, for a disagreement.
    pub fn dropped_reason(&self) -> Option<String> {
        match self {
            Check::Disagrees {
                live_pairs,
                median_residual_m,
                bound_m,
            } => Some(format!(
                "the live pairs are {median_residual_m:.2} m from it (median of {live_pairs}), more than {bound_m:.2} m"
            )),
            _ => None,
        }
    }
}

/// Checks the restored pairs (`old`) against the live ones: the old pairs
/// alone are fitted and the live pairs' median residual under that fit is
/// compared with `continuity.disagreement_factor` times the fit's own RMS
/// (at least the alignment's inlier threshold). None when there are no
/// old pairs (or no residual to take a median of).
pub fn check_saved(old: &[Pair], live: &[Pair], params: &Params) -> Option<Check> {
    let cp = &params.continuity;
    if old.is_empty() {
        return None;
    }
    let needed = cp.min_live_pairs.max(1);
    if live.len() < needed {
        return Some(Check::Waiting {
            live_pairs: live.len(),
            needed,
        });
    }
    let fit = match fit_pairs(old, &params.align, None, params.align.seed) {
        Ok(f) => f,
        Err(e) => {
            return Some(Check::Unfitted {
                reason: e.to_string(),
            });
        }
    };
    let residuals: Vec<f64> = live
        .iter()
        .map(|p| (fit.ned_from_map.transform_point(&p.p_map) - p.p_ned).norm())
        .collect();
    let median = crate::stats::median(&residuals)?;
    let bound = (cp.disagreement_factor * fit.quality.rms_m).max(params.align.inlier_threshold_m);
    let (live_pairs, median_residual_m, bound_m) = (live.len(), median, bound);
    Some(if median <= bound {
        Check::Agrees {
            live_pairs,
            median_residual_m,
            bound_m,
        }
    } else {
        Check::Disagrees {
            live_pairs,
            median_residual_m,
            bound_m,
        }
    })
}

#[cfg(test)]
mod tests {
    use super::*;
    use nalgebra::{Point3, UnitQuaternion, Vector3};

    const HOME: Geodetic = Geodetic {
        lat_deg: 47.3977,
        lon_deg: 8.5456,
        alt_m: 488.0,
    };

    fn saved_pair(id: u64, anchor_kf: u64, anchor_time: f64) -> SavedPair {
        SavedPair {
            id,
            kind: PairKind::Frame,
            anchor_kf,
            anchor_time,
            cam_from_anchor: SavedPose::from_isometry(&Isometry3::translation(0.0, 0.0, 1.0)),
            time: anchor_time + 0.5,
            ned_from_cam: SavedPose::from_isometry(&Isometry3::translation(3.0, 4.0, -10.0)),
            v_ned: Some([1.0, 0.0, 0.0]),
        }
    }

    fn restore(pairs: Vec<SavedPair>) -> Restore {
        Restore::from_saved(SavedGeoreference {
            format: SAVED_FORMAT,
            saved_unix: 1.0,
            home: HOME,
            pairs,
            fit: None,
        })
        .unwrap()
    }

    /// A pair is placed through its anchor keyframe only when that
    /// keyframe has the saved capture time; a held pair saved from its
    /// anchor comes back as it was.
    #[test]
    fn saved_pairs_are_placed_on_their_anchor_keyframe_only() {
        let p = saved_pair(1 << 63 | 5, 4, 10.0);
        let world_from_kf = Isometry3::translation(1.0, 2.0, 3.0);
        let mut poses = KeyframePoses::new();
        poses.insert(4, (10.0, world_from_kf));
        let (map_from_cam, ned) = place(&p, &poses).unwrap();
        // cam ← kf is 1 m along z: the camera's centre is 1 m behind.
        assert!((map_from_cam.translation.vector - Vector3::new(1.0, 2.0, 2.0)).norm() < 1e-12);
        assert_eq!(ned.translation.vector, Vector3::new(3.0, 4.0, -10.0));
        poses.insert(4, (10.5, world_from_kf));
        assert!(place(&p, &poses).is_none(), "another keyframe with that id");
        assert!(place(&p, &KeyframePoses::new()).is_none());

        let a = Anchor::of_saved(&p);
        assert_eq!((a.kind, a.kf, a.kf_time), (PairKind::Frame, 4, 10.0));
        let held = Pair {
            kf_id: p.id,
            p_map: Point3::from(map_from_cam.translation.vector),
            p_ned: Point3::from(ned.translation.vector),
            time: p.time,
            orientations: Some((map_from_cam.rotation, ned.rotation)),
            v_ned: p.v_ned.map(Vector3::from),
        };
        assert_eq!(a.saved_pair(&held), Some(p));
        let no_orientation = Pair {
            orientations: None,
            ..held
        };
        assert_eq!(a.saved_pair(&no_orientation), None);
    }

    /// The waiting pairs wait for the map's fate, go when it was not
    /// continued and are all taken when it was; a file of another format
    /// is not taken at all; another home carries them there.
    #[test]
    fn waiting_pairs_follow_the_maps_fate_and_the_vehicles_home() {
        let mut r = restore(vec![saved_pair(1, 1, 1.0), saved_pair(2, 2, 2.0)]);
        assert_eq!(r.take_waiting(None, true), None);
        assert_eq!(r.take_waiting(Some(true), false), None);
        assert_eq!(r.take_waiting(Some(true), true).map(|w| w.len()), Some(2));
        assert!(r.waiting.is_empty());

        let mut r = restore(vec![saved_pair(1, 1, 1.0)]);
        assert_eq!(r.take_waiting(Some(false), true), None);
        assert_eq!((r.unmatched, r.waiting.len()), (1, 0));
        assert!(r.dropped.is_some());
        assert_eq!(
            serde_json::to_value(r.status(None)).unwrap()["unmatched"],
            1
        );

        let other = SavedGeoreference {
            format: SAVED_FORMAT + 1,
            saved_unix: 0.0,
            home: HOME,
            pairs: vec![],
            fit: None,
        };
        assert!(Restore::from_saved(other).is_none());

        let mut r = restore(vec![saved_pair(1, 1, 1.0)]);
        assert_eq!(r.rebase(HOME), 0.0);
        assert_eq!(r.home_moved_m, Some(0.0));
        let north = LocalFrame::new(HOME).ned_to_geodetic(&Vector3::new(10.0, 0.0, 0.0));
        let moved = r.rebase(north);
        assert!((moved - 10.0).abs() < 1e-6, "{moved}");
        let p = r.waiting[0].ned_from_cam.to_isometry().unwrap();
        // The camera was 3 m north of the old home: 7 m south of the new.
        assert!((p.translation.x + 7.0).abs() < 1e-3, "{p}");
    }

    /// Pairs related by a known similarity: live pairs that agree with
    /// the saved ones, and live pairs 5 m off.
    #[test]
    fn live_pairs_agree_with_the_saved_ones_or_not() {
        let pair = |id: u64, p_map: Point3<f64>, offset: f64| Pair {
            kf_id: id,
            p_map,
            p_ned: Point3::new(2.0 * p_map.x + offset, 2.0 * p_map.y, 2.0 * p_map.z),
            time: id as f64,
            orientations: Some((UnitQuaternion::identity(), UnitQuaternion::identity())),
            v_ned: None,
        };
        let grid = |from: u64, offset: f64| -> Vec<Pair> {
            (0..12)
                .map(|i| {
                    let p = Point3::new((i % 4) as f64 * 3.0, (i / 4) as f64 * 4.0, (i % 3) as f64);
                    pair(from + i, p, offset)
                })
                .collect()
        };
        let params = Params::default();
        let old = grid(0, 0.0);
        assert_eq!(check_saved(&[], &old, &params), None);
        let few = check_saved(&old, &grid(100, 0.0)[..1], &params);
        assert!(
            matches!(few, Some(Check::Waiting { live_pairs: 1, .. })),
            "{few:?}"
        );
        let agrees = check_saved(&old, &grid(100, 0.0), &params).unwrap();
        assert!(matches!(agrees, Check::Agrees { .. }), "{agrees:?}");
        assert_eq!(agrees.dropped_reason(), None);
        let disagrees = check_saved(&old, &grid(100, 5.0), &params).unwrap();
        match &disagrees {
            Check::Disagrees {
                median_residual_m, ..
            } => assert!((median_residual_m - 5.0).abs() < 1e-6),
            c => panic!("{c:?}"),
        }
        assert!(disagrees.dropped_reason().unwrap().contains("5.00 m"));
        let unfitted = check_saved(&old[..1], &grid(100, 0.0), &params);
        assert!(
            matches!(unfitted, Some(Check::Unfitted { .. })),
            "{unfitted:?}"
        );
    }
}
