//! The global bundle adjustment after a loop (off by default,
//! `LoopParams::global_ba`): every keyframe and point of the loop's map, its
//! root fixed; the problem built and written back under the map lock with
//! local mapping held for the write, solved without either; each hold of
//! the lock recorded ([`LockHold`], [`HoldKind::GlobalBa`]).

use std::sync::Mutex;
use std::time::Instant;

use crate::optimize::BaParams;
use crate::slam::bundle::{apply_ba_result, build_ba_problem};
use crate::slam::map::{KeyFrameId, Map, lock};
use crate::slam::pause::MappingPause;

use super::log::{HoldKind, LockHold};

/// Bundle adjustment over every keyframe and point of `kf`'s map, the
/// map's first keyframe fixed: the problem is built and written back under the map
/// lock, solved without it (keyframes added meanwhile keep their poses).
/// Returns the final reprojection RMSE, px.
pub(super) fn global_bundle_adjustment(
    map: &Mutex<Map>,
    kf: KeyFrameId,
    params: &BaParams,
    pause: Option<&MappingPause>,
    holds: &mut Vec<LockHold>,
) -> Option<f64> {
    let mut setup = {
        let m = lock(map);
        let from = Instant::now();
        let _hold = HoldGuard {
            holds: &mut *holds,
            kf,
            from,
        };
        let id = m.map_of(kf)?;
        let kfs: Vec<KeyFrameId> = m.keyframes_in(id).map(|k| k.id).collect();
        let fixed: Vec<KeyFrameId> = m.root_of(id).into_iter().collect();
        if kfs.len() < 2 {
            return None;
        }
        build_ba_problem(&m, &kfs, &fixed)?
    };
    let report = crate::optimize::local_bundle_adjustment(&mut setup.problem, params).ok()?;
    tracing::debug!(
        keyframes = setup.keyframes.len(),
        points = setup.points.len(),
        before = report.initial_rmse_px,
        after = report.final_rmse_px,
        outliers = report.n_outliers,
        "loop: global BA"
    );
    // Solved beside local mapping; written back with it held (its
    // adjustments made meanwhile give way to the global solution).
    let held = pause.map(MappingPause::hold);
    let mut m = lock(map);
    let from = Instant::now();
    apply_ba_result(&mut m, &setup, &report.outliers);
    m.note_correction();
    drop(m);
    drop(held);
    holds.push(LockHold {
        kf,
        from,
        to: Instant::now(),
        kind: HoldKind::GlobalBa,
    });
    Some(report.final_rmse_px)
}

/// Records a global BA's lock hold when dropped (every return of the
/// block that builds the problem).
struct HoldGuard<'a> {
    holds: &'a mut Vec<LockHold>,
    kf: KeyFrameId,
    from: Instant,
}

impl Drop for HoldGuard<'_> {
    fn drop(&mut self) {
        self.holds.push(LockHold {
            kf: self.kf,
            from: self.from,
            to: Instant::now(),
            kind: HoldKind::GlobalBa,
        });
    }
}
