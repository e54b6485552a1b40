//! Fuzz the body of `POST /api/v1/shots`: the JSON parsing and checks
//! (`shotpilot::api::parse_shot_request`), then the anchor validation and
//! the desired-shot warp (`shotpilot::shot::request::anchor_shot`, i.e.
//! `shotpilot::shot`'s) on a small synthetic keyframe.
//!
//! Checked: no panic; every refusal is a 4xx with a known code; a request
//! that passes makes a desired shot of exactly the asked size, and a
//! keyframe-size shot whose homography takes the frame's corner pixels
//! onto the anchors.
#![no_main]

use std::sync::Arc;

use image::{GrayImage, Luma};
use libfuzzer_sys::fuzz_target;
use nalgebra::Point2;
use shotpilot::api::parse_shot_request;
use shotpilot::geometry::homography4::apply_homography;
use shotpilot::shot::request::{KeyframeImages, Params, ShotRequestError, WarpOnly};

/// Keyframe 0 does not exist; every other id is one 64x48 picture.
struct OneKeyframe(Arc<GrayImage>);

impl KeyframeImages for OneKeyframe {
    fn keyframe_image(&self, id: u64) -> Option<Arc<GrayImage>> {
        (id != 0).then(|| self.0.clone())
    }
}

const W: u32 = 64;
const H: u32 = 48;

fuzz_target!(|data: &[u8]| {
    let (kf, anchors, size) = match parse_shot_request(data) {
        Ok(p) => p,
        Err(e) => {
            assert_eq!(e.status().as_u16(), 400, "{e:?}");
            assert!(
                matches!(e.code(), "bad_json" | "bad_anchors" | "bad_size"),
                "{e:?}"
            );
            return;
        }
    };
    let img = GrayImage::from_fn(W, H, |x, y| Luma([((x * 7 + y * 13) % 251) as u8]));
    let computer = WarpOnly {
        keyframes: OneKeyframe(Arc::new(img)),
        // A small output cap keeps each run fast; the default's checks are
        // the same code.
        params: Params {
            max_output_side: 96,
            ..Params::default()
        },
    };
    match computer.anchor_shot(kf, &anchors, size) {
        Err(ShotRequestError::UnknownKeyframe { id }) => assert_eq!((id, kf), (0, 0)),
        Err(e @ ShotRequestError::BadAnchors { .. })
        | Err(e @ ShotRequestError::BadImage { .. }) => {
            assert!(!e.to_string().is_empty());
        }
        Err(e) => panic!("unexpected refusal {e:?}"),
        Ok(shot) => {
            assert_ne!(kf, 0);
            assert_eq!(shot.picture().dimensions(), size.unwrap_or((W, H)));
            assert_eq!(shot.shot.image.dimensions(), (W, H));
            // The homography takes the frame's corner pixels onto the anchors.
            let h = shot.shot.shot_to_source;
            let (w, hh) = ((W - 1) as f64, (H - 1) as f64);
            let corners = [(0.0, 0.0), (w, 0.0), (w, hh), (0.0, hh)];
            for (c, a) in corners.iter().zip(&anchors) {
                let q = apply_homography(&h, &Point2::new(c.0, c.1))
                    .expect("a corner maps to a finite point");
                let err = ((q.x - a[0]).powi(2) + (q.y - a[1]).powi(2)).sqrt();
                assert!(
                    err < 1e-6 * (1.0 + W.max(H) as f64),
                    "corner {c:?} -> {q} vs {a:?}: {err}"
                );
            }
        }
    }
});
