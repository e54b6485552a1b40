//! `shotpilot shot`: the desired shot (from anchors on a keyframe, or a
//! photo) and the camera pose that takes it, in map coordinates.

use std::path::PathBuf;
use std::time::Instant;

use anyhow::{Context, Result, bail};
use clap::Args;
use nalgebra::Point2;
use serde_json::json;

use shotpilot::camera::{Camera, Distortion};
use shotpilot::shot::{self, Localization};
use shotpilot::slam::{KeyFrameId, mapfile};

/// Arguments of `shotpilot shot`.
#[derive(Args, Debug)]
pub struct ShotArgs {
    /// Map file (from `shotpilot slam --save-map`).
    #[arg(long, value_name = "FILE")]
    pub map: PathBuf,
    /// Keyframe whose image the anchors are placed on.
    #[arg(
        long,
        value_name = "ID",
        requires = "anchors",
        conflicts_with = "photo"
    )]
    pub keyframe: Option<u32>,
    /// The four anchors, pixels of the keyframe: where the frame's top-left,
    /// top-right, bottom-right and bottom-left corners should go.
    #[arg(
        long,
        value_name = "x1,y1,x2,y2,x3,y3,x4,y4",
        requires = "keyframe",
        allow_hyphen_values = true
    )]
    pub anchors: Option<String>,
    /// A photo of the desired shot (JPEG or PNG; turned upright by its
    /// EXIF orientation): its camera from --photo-intrinsics, else from its
    /// EXIF focal length (focal-plane resolution or 35 mm equivalent; the
    /// focal length and distortion are then estimated with the pose), else
    /// the map's camera (at another size, same aspect ratio: a resized copy).
    #[arg(long, value_name = "FILE")]
    pub photo: Option<PathBuf>,
    /// The photo's camera when it is not the map's: `fx,fy,cx,cy` or
    /// `fx,fy,cx,cy,k1,k2,p1,p2,k3` (pixels of the photo, OpenCV order).
    #[arg(long, value_name = "fx,fy,cx,cy[,k1,k2,p1,p2,k3]", requires = "photo")]
    pub photo_intrinsics: Option<String>,
    /// Folder for desired_shot.png (and desired_shot_mask.png).
    #[arg(long, value_name = "DIR")]
    pub out: Option<PathBuf>,
    /// Candidate keyframes tried.
    #[arg(long, default_value_t = 5, value_name = "K")]
    pub top_k: usize,
    /// Choose the candidates by a bag-of-words query with the built-in
    /// vocabulary instead of descriptor matching against every keyframe.
    #[arg(long)]
    pub bow: bool,
    /// Seed of the RANSAC.
    #[arg(long, default_value_t = 1, value_name = "N")]
    pub seed: u64,
    /// Print exactly one JSON object on stdout instead of text.
    #[arg(long)]
    pub json: bool,
}

/// Parses `x1,y1,x2,y2,x3,y3,x4,y4`.
fn parse_anchors(s: &str) -> Result<[Point2<f64>; 4]> {
    let v: Vec<f64> = s
        .split(',')
        .map(|t| {
            t.trim()
                .parse::<f64>()
                .with_context(|| format!("anchor value {t:?} is not a number"))
        })
        .collect::<Result<_>>()?;
    if v.len() != 8 {
        bail!(
            "--anchors needs 8 numbers (x1,y1,...,x4,y4), got {}",
            v.len()
        );
    }
    Ok([
        Point2::new(v[0], v[1]),
        Point2::new(v[2], v[3]),
        Point2::new(v[4], v[5]),
        Point2::new(v[6], v[7]),
    ])
}

/// Parses `fx,fy,cx,cy[,k1,k2,p1,p2,k3]` into the camera of a `w` x `h` photo.
fn parse_intrinsics(s: &str, w: u32, h: u32) -> Result<Camera> {
    let v: Vec<f64> = s
        .split(',')
        .map(|t| {
            t.trim()
                .parse::<f64>()
                .with_context(|| format!("intrinsics value {t:?} is not a number"))
        })
        .collect::<Result<_>>()?;
    let distortion = match v.len() {
        4 => Distortion::default(),
        9 => Distortion {
            k1: v[4],
            k2: v[5],
            p1: v[6],
            p2: v[7],
            k3: v[8],
        },
        n => bail!("--photo-intrinsics needs 4 or 9 numbers, got {n}"),
    };
    Camera::new(w, h, [v[0], v[1], v[2], v[3]], distortion)
        .context("--photo-intrinsics are not a usable camera")
}

/// Keyframes listed for a shot that was not localised.
const NEAREST_KEYFRAMES: usize = 3;

/// Makes the desired shot, localises it in the map and prints the result.
pub fn run(args: ShotArgs) -> Result<()> {
    let t0 = Instant::now();
    let map =
        mapfile::load(&args.map).with_context(|| format!("loading map {}", args.map.display()))?;
    let cam = map.camera;
    let mut params = shot::Params {
        localize: shot::LocalizeParams {
            seed: args.seed,
            top_k: args.top_k,
            ..shot::LocalizeParams::default()
        },
        ..shot::Params::default()
    };

    let mut intrinsics_source = None;
    // An anchors shot's keyframe and transform: its camera comes from the
    // keyframe's geometry, as in the daemon.
    let mut anchored_on = None;
    let (image, mask, shot_cam, source) = match (&args.photo, args.keyframe, &args.anchors) {
        (Some(photo), None, None) => {
            let bytes = std::fs::read(photo)
                .with_context(|| format!("reading photo {}", photo.display()))?;
            // Upright by its EXIF orientation; intrinsics given, else from
            // its EXIF, else the map camera's scaled.
            let decoded = shot::decode_photo(&bytes)
                .with_context(|| format!("reading photo {}", photo.display()))?;
            if let Some(w) = &decoded.exif_warning {
                eprintln!("photo {}: EXIF ignored: {w}", photo.display());
            }
            let (w, h) = decoded.image.dimensions();
            let given = match &args.photo_intrinsics {
                Some(s) => Some(parse_intrinsics(s, w, h)?),
                None => None,
            };
            let pc = shot::photo_camera(&cam, &decoded, given).with_context(|| {
                format!(
                    "photo {} is {w}x{h}, the map's camera {}x{}, and its EXIF gives no focal length: give --photo-intrinsics",
                    photo.display(),
                    cam.width,
                    cam.height
                )
            })?;
            params.localize.camera_uncertainty = pc.uncertainty;
            params.localize.focal_unknown = pc.focal_unknown;
            intrinsics_source = Some(pc.source);
            (decoded.image, None, pc.camera, "photo")
        }
        (None, Some(id), Some(anchors)) => {
            let anchors = parse_anchors(anchors)?;
            let Some(kf) = map.keyframe(KeyFrameId(id)) else {
                let mut ids: Vec<u32> = map.keyframes().map(|k| k.id.0).collect();
                ids.sort_unstable();
                return Err(shot::ShotError::UnknownKeyFrame { id })
                    .with_context(|| format!("the map's keyframes are {ids:?}"));
            };
            let img = kf.image.as_ref().ok_or(shot::ShotError::NoImage { id })?;
            let d = shot::desired_shot_from_anchors(img, &anchors, &params.anchors)
                .context("the anchors were refused")?;
            anchored_on = Some((KeyFrameId(id), d.shot_to_source));
            (d.image, Some(d.mask), cam, "anchors")
        }
        _ => bail!("give either --keyframe ID with --anchors, or --photo FILE"),
    };
    let t_shot = t0.elapsed().as_secs_f64() * 1e3;

    let mut shot_path = None;
    if let Some(dir) = &args.out {
        std::fs::create_dir_all(dir).with_context(|| format!("creating {}", dir.display()))?;
        let p = dir.join("desired_shot.png");
        image
            .save(&p)
            .with_context(|| format!("writing {}", p.display()))?;
        if let Some(m) = &mask {
            let mp = dir.join("desired_shot_mask.png");
            m.save(&mp)
                .with_context(|| format!("writing {}", mp.display()))?;
        }
        shot_path = Some(p);
    }

    let t1 = Instant::now();
    let vocabulary = if args.bow {
        Some(shotpilot::bow::Vocabulary::builtin().context("loading the built-in vocabulary")?)
    } else {
        None
    };
    let index = vocabulary.as_ref().map(|v| shot::BowIndex::build(&map, v));
    let result = match anchored_on {
        Some((id, h)) => shot::localize_anchors(&map, id, &h, &params.localize),
        None => shot::localize_with_camera(
            &map,
            &shot_cam,
            &image,
            mask.as_ref(),
            index.as_ref(),
            &params.localize,
        )?,
    };
    let t_loc = t1.elapsed().as_secs_f64() * 1e3;
    // Not localised: the keyframes the shot resembles most, by BoW score,
    // with where they are ("fly towards here").
    let nearest = match &result {
        Localization::Localized(_) => Vec::new(),
        Localization::NotLocalized { .. } => {
            let own;
            let own_index;
            let idx = match &index {
                Some(i) => i,
                None => {
                    own = shotpilot::bow::Vocabulary::builtin()
                        .context("loading the built-in vocabulary")?;
                    own_index = shot::BowIndex::build(&map, &own);
                    &own_index
                }
            };
            shot::nearest_keyframes(
                &map,
                &shot_cam,
                &image,
                mask.as_ref(),
                idx,
                &params.localize,
                NEAREST_KEYFRAMES,
            )?
        }
    };
    let nearest_json: Vec<serde_json::Value> = nearest
        .iter()
        .map(|n| {
            json!({
                "keyframe_id": n.keyframe_id.0,
                "score": n.score,
                "position": [n.position.x, n.position.y, n.position.z],
            })
        })
        .collect();
    // Metres per map unit, when a georeference was saved beside the map.
    let metres_per_unit = shotpilot::daemon::persist::load_geo(&args.map)
        .and_then(|g| g.fit)
        .map(|f| f.scale)
        .filter(|s| s.is_finite() && *s > 0.0);

    let shot_path_str = shot_path
        .as_ref()
        .map(|p: &PathBuf| p.display().to_string());
    let value = match &result {
        Localization::Localized(p) => {
            let t = p.world_from_cam.translation.vector;
            let q = p.world_from_cam.rotation;
            json!({
                "localized": true,
                "reason": null,
                "source": source,
                "candidates_by": if args.bow { "bow" } else { "descriptors" },
                "position": [t.x, t.y, t.z],
                "quaternion": [q.i, q.j, q.k, q.w],
                "inliers": p.inliers,
                "matches": p.matches,
                "inlier_ratio": p.inlier_ratio,
                "reprojection_rmse_px": p.reprojection_rmse_px,
                "median_depth": p.median_depth,
                "agreeing_candidates": p.agreeing_candidates,
                "beyond_views_deg": p.beyond_views_deg,
                "position_sigma": p.sigma.position,
                "position_sigma_m": metres_per_unit.map(|k| k * p.sigma.position),
                "position_sigma_fraction_of_distance": p.sigma.position_depth_fraction,
                "rotation_sigma_deg": p.sigma.rotation_deg,
                "intrinsics_source": intrinsics_source.map(|s| s.as_str()),
                "keyframe_id": p.keyframe_id.0,
                "desired_shot": shot_path_str,
                "shot_ms": t_shot,
                "localize_ms": t_loc,
            })
        }
        Localization::NotLocalized { reason } => json!({
            "localized": false,
            "reason": reason.to_string(),
            "source": source,
            "position": null,
            "quaternion": null,
            "inliers": null,
            "reprojection_rmse_px": null,
            "keyframe_id": null,
            "nearest_keyframes": nearest_json,
            "intrinsics_source": intrinsics_source.map(|s| s.as_str()),
            "desired_shot": shot_path_str,
            "shot_ms": t_shot,
            "localize_ms": t_loc,
        }),
    };
    if args.json {
        println!("{value}");
    } else {
        match &result {
            Localization::Localized(p) => {
                let t = p.world_from_cam.translation.vector;
                let q = p.world_from_cam.rotation;
                println!(
                    "localised through keyframe {}: position [{:.4}, {:.4}, {:.4}], quaternion [{:.5}, {:.5}, {:.5}, {:.5}] (world_from_cam)",
                    p.keyframe_id.0, t.x, t.y, t.z, q.i, q.j, q.k, q.w
                );
                println!(
                    "{} inliers of {} pairs, reprojection RMSE {:.3} px, median depth {:.3}, {} agreeing candidates, {:.1} deg beyond the flown views",
                    p.inliers,
                    p.matches,
                    p.reprojection_rmse_px,
                    p.median_depth,
                    p.agreeing_candidates,
                    p.beyond_views_deg
                );
                let metres = metres_per_unit
                    .map(|k| format!(" = {:.3} m", k * p.sigma.position))
                    .unwrap_or_default();
                println!(
                    "sigma: position {:.4} map units{metres} ({:.2} % of the distance to the nearest scene), rotation {:.3} deg",
                    p.sigma.position,
                    p.sigma.position_depth_fraction * 100.0,
                    p.sigma.rotation_deg
                );
            }
            Localization::NotLocalized { reason } => {
                println!("not localised: {reason}");
                if !nearest.is_empty() {
                    println!("the photo looks most like these keyframes (fly towards them):");
                }
                for n in &nearest {
                    println!(
                        "  keyframe {}: BoW score {:.3}, at [{:.3}, {:.3}, {:.3}] (map)",
                        n.keyframe_id.0, n.score, n.position.x, n.position.y, n.position.z
                    );
                }
            }
        }
        if let Some(p) = &shot_path {
            println!("desired shot written to {}", p.display());
        }
        println!("desired shot {t_shot:.1} ms (incl. map load), localisation {t_loc:.1} ms");
    }
    Ok(())
}
