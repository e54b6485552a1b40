//! A PNG of an evaluation: the top view of both trajectories (ground truth
//! and aligned estimate) and the position error over time.
//!
//! Text needs a TrueType font; the first of a few common system fonts is
//! used (DejaVu Sans, Liberation Sans, Noto Sans). Without any, the plot is
//! drawn without labels and a warning is logged.

use std::path::{Path, PathBuf};

use plotters::prelude::*;
use plotters::style::FontStyle;

use super::Evaluation;

/// Errors drawing a plot.
#[derive(Debug, thiserror::Error)]
pub enum PlotError {
    /// Drawing failed.
    #[error("cannot draw plot: {0}")]
    Draw(String),
    /// Writing the PNG failed.
    #[error("cannot write plot {path}: {reason}")]
    Write {
        /// The file.
        path: PathBuf,
        /// Why.
        reason: String,
    },
}

const FONT_CANDIDATES: &[&str] = &[
    "/usr/share/fonts/truetype/dejavu/DejaVuSans.ttf",
    "/usr/share/fonts/TTF/DejaVuSans.ttf",
    "/usr/share/fonts/dejavu/DejaVuSans.ttf",
    "/usr/share/fonts/truetype/liberation/LiberationSans-Regular.ttf",
    "/usr/share/fonts/truetype/noto/NotoSans-Regular.ttf",
    "/System/Library/Fonts/Supplemental/Arial.ttf",
    "C:\\Windows\\Fonts\\arial.ttf",
];

/// Register a system font with plotters under "sans-serif"; false if none found.
fn register_system_font() -> bool {
    for path in FONT_CANDIDATES {
        if let Ok(bytes) = std::fs::read(path) {
            // plotters keeps registered fonts for the life of the process.
            let bytes: &'static [u8] = Box::leak(bytes.into_boxed_slice());
            if plotters::style::register_font("sans-serif", FontStyle::Normal, bytes).is_ok() {
                return true;
            }
        }
    }
    false
}

fn draw_err<E: std::fmt::Debug>(e: E) -> PlotError {
    PlotError::Draw(format!("{e:?}"))
}

/// Draw `eval` into a PNG at `path` (1400 x 600 pixels).
pub fn plot_evaluation(eval: &Evaluation, path: &Path, title: &str) -> Result<(), PlotError> {
    let (w, h) = (1400u32, 600u32);
    let has_font = register_system_font();
    if !has_font {
        tracing::warn!("no TrueType font found; the plot has no labels");
    }
    let mut buf = vec![255u8; (w * h * 3) as usize];
    {
        let root = BitMapBackend::with_buffer(&mut buf, (w, h)).into_drawing_area();
        root.fill(&WHITE).map_err(draw_err)?;
        let (left, right) = root.split_horizontally(620);

        // Top view: the two axes along which the ground truth spreads most.
        let spread = |k: usize| {
            let v: Vec<f64> = eval.gt_positions.iter().map(|p| p[k]).collect();
            let lo = v.iter().copied().fold(f64::INFINITY, f64::min);
            let hi = v.iter().copied().fold(f64::NEG_INFINITY, f64::max);
            hi - lo
        };
        let mut axes = [0usize, 1, 2];
        axes.sort_by(|&a, &b| spread(b).total_cmp(&spread(a)));
        let (ax, ay) = (axes[0], axes[1]);
        let pts = eval.gt_positions.iter().chain(&eval.est_positions);
        let (mut x0, mut x1, mut y0, mut y1) = (
            f64::INFINITY,
            f64::NEG_INFINITY,
            f64::INFINITY,
            f64::NEG_INFINITY,
        );
        for p in pts {
            x0 = x0.min(p[ax]);
            x1 = x1.max(p[ax]);
            y0 = y0.min(p[ay]);
            y1 = y1.max(p[ay]);
        }
        // Equal scale on both axes.
        let half = 0.5 * (x1 - x0).max(y1 - y0).max(1e-6) * 1.08;
        let (xc, yc) = (0.5 * (x0 + x1), 0.5 * (y0 + y1));
        let names = ["x", "y", "z"];
        let mut top = ChartBuilder::on(&left);
        top.margin(15);
        if has_font {
            top.caption(
                format!("{title}: top view ({} / {})", names[ax], names[ay]),
                ("sans-serif", 18),
            )
            .x_label_area_size(35)
            .y_label_area_size(55);
        }
        let mut top = top
            .build_cartesian_2d(xc - half..xc + half, yc - half..yc + half)
            .map_err(draw_err)?;
        let mut mesh = top.configure_mesh();
        if has_font {
            mesh.x_desc(format!("{} [m]", names[ax]))
                .y_desc(format!("{} [m]", names[ay]));
        } else {
            mesh.x_labels(0).y_labels(0);
        }
        mesh.draw().map_err(draw_err)?;
        let gt_series = top
            .draw_series(LineSeries::new(
                eval.gt_positions.iter().map(|p| (p[ax], p[ay])),
                BLACK.stroke_width(2),
            ))
            .map_err(draw_err)?;
        if has_font {
            gt_series.label("ground truth").legend(|(x, y)| {
                PathElement::new(vec![(x, y), (x + 20, y)], BLACK.stroke_width(2))
            });
        }
        let est_series = top
            .draw_series(LineSeries::new(
                eval.est_positions.iter().map(|p| (p[ax], p[ay])),
                BLUE.stroke_width(1),
            ))
            .map_err(draw_err)?;
        if has_font {
            est_series
                .label("estimate (aligned)")
                .legend(|(x, y)| PathElement::new(vec![(x, y), (x + 20, y)], BLUE.stroke_width(2)));
            top.configure_series_labels()
                .position(SeriesLabelPosition::UpperLeft)
                .background_style(WHITE.mix(0.8))
                .border_style(BLACK)
                .draw()
                .map_err(draw_err)?;
        }

        // Error over time.
        let t0 = eval.errors.first().map_or(0.0, |e| e.0);
        let t1 = eval.errors.last().map_or(1.0, |e| e.0).max(t0 + 1e-6);
        let emax = eval.ate.max.max(1e-9) * 1.1;
        let mut err = ChartBuilder::on(&right);
        err.margin(15);
        if has_font {
            err.caption(
                format!(
                    "position error: RMSE {:.4} m, max {:.4} m, {} poses",
                    eval.ate.rmse, eval.ate.max, eval.matched
                ),
                ("sans-serif", 18),
            )
            .x_label_area_size(35)
            .y_label_area_size(65);
        }
        let mut err = err
            .build_cartesian_2d(0.0..t1 - t0, 0.0..emax)
            .map_err(draw_err)?;
        let mut mesh = err.configure_mesh();
        if has_font {
            mesh.x_desc("time [s]").y_desc("error [m]");
        } else {
            mesh.x_labels(0).y_labels(0);
        }
        mesh.draw().map_err(draw_err)?;
        err.draw_series(LineSeries::new(
            eval.errors.iter().map(|&(t, e)| (t - t0, e)),
            RED.stroke_width(2),
        ))
        .map_err(draw_err)?;
        err.draw_series(LineSeries::new(
            [(0.0, eval.ate.rmse), (t1 - t0, eval.ate.rmse)],
            RED.mix(0.4).stroke_width(1),
        ))
        .map_err(draw_err)?;
        root.present().map_err(draw_err)?;
    }
    let img = image::RgbImage::from_raw(w, h, buf)
        .ok_or_else(|| PlotError::Draw("buffer size".into()))?;
    img.save(path).map_err(|e| PlotError::Write {
        path: path.to_owned(),
        reason: e.to_string(),
    })
}
