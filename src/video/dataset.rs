//! Offline frame sources: TUM RGB-D layout and EuRoC ASL layout.
//!
//! **TUM layout** (also what `shotpilot-sim render` writes): `rgb.txt` with
//! lines `timestamp rgb/<file>`, `calib.txt` with one line
//! `fx fy cx cy k1 k2 p1 p2 k3`, optional `groundtruth.txt` in the TUM
//! trajectory format. `#` starts a comment everywhere.
//!
//! **EuRoC ASL layout**: `mav0/cam0/data.csv` (`#timestamp [ns],filename`),
//! images in `mav0/cam0/data/`, intrinsics, distortion, resolution and the
//! body-to-camera transform `T_BS` in `mav0/cam0/sensor.yaml`; ground truth
//! (optional) in `mav0/state_groundtruth_estimate0/data.csv` as body poses,
//! turned into camera poses with `T_BS`. The path given may be the dataset
//! root, its `mav0` folder or the `cam0` folder.
//!
//! Every frame is returned as 8-bit grayscale (RGB converted with the Rec.601
//! luma weights `image` uses). A missing file, an unreadable image or a
//! malformed line is an error naming the file (and line); nothing is skipped.

use std::path::{Path, PathBuf};

use image::GrayImage;
use nalgebra::{Isometry3, Matrix3, Matrix4, Quaternion, Rotation3, Translation3, UnitQuaternion};

use crate::camera::{Camera, CameraError, Distortion};
use crate::trajectory::{StampedPose, Trajectory, TrajectoryError};

/// Errors of the dataset readers.
#[derive(Debug, thiserror::Error)]
pub enum DatasetError {
    /// The path is neither a TUM nor a EuRoC dataset.
    #[error(
        "{path}: not a dataset (expected rgb.txt + calib.txt (TUM layout) or mav0/cam0/data.csv (EuRoC layout))"
    )]
    UnknownLayout {
        /// The folder.
        path: PathBuf,
    },
    /// A file that the layout requires is missing or unreadable.
    #[error("cannot read {path}: {source}")]
    Io {
        /// The file.
        path: PathBuf,
        /// The cause.
        source: std::io::Error,
    },
    /// A line of an index or calibration file is malformed.
    #[error("{path}:{line}: {reason}")]
    Parse {
        /// The file.
        path: PathBuf,
        /// 1-based line number.
        line: usize,
        /// What is wrong.
        reason: String,
    },
    /// An image could not be decoded.
    #[error("cannot decode image {path}: {reason}")]
    Image {
        /// The image file.
        path: PathBuf,
        /// The decoder's message.
        reason: String,
    },
    /// An image has another size than the calibration says.
    #[error("{path}: image is {found_w}x{found_h}, expected {expected_w}x{expected_h}")]
    ImageSize {
        /// The image file.
        path: PathBuf,
        /// Its width.
        found_w: u32,
        /// Its height.
        found_h: u32,
        /// Expected width.
        expected_w: u32,
        /// Expected height.
        expected_h: u32,
    },
    /// The calibration could not be read.
    #[error(transparent)]
    Camera(#[from] CameraError),
    /// The ground truth could not be read.
    #[error(transparent)]
    Trajectory(#[from] TrajectoryError),
    /// The index lists no frame.
    #[error("{path}: lists no frames")]
    Empty {
        /// The index file.
        path: PathBuf,
    },
    /// A frame index beyond the end.
    #[error("frame {index} requested, dataset has {len}")]
    OutOfRange {
        /// Requested index.
        index: usize,
        /// Number of frames.
        len: usize,
    },
}

/// The layout a dataset was read from.
#[derive(Debug, Clone, Copy, PartialEq, Eq, serde::Serialize)]
#[serde(rename_all = "lowercase")]
pub enum Layout {
    /// TUM RGB-D (`rgb.txt`, `calib.txt`, `groundtruth.txt`).
    Tum,
    /// EuRoC ASL (`mav0/cam0/data.csv`, `sensor.yaml`).
    Euroc,
}

/// One frame: its capture time and grayscale image.
#[derive(Debug, Clone)]
pub struct Frame {
    /// Position in the dataset, from 0.
    pub index: usize,
    /// Capture time, seconds.
    pub timestamp: f64,
    /// 8-bit grayscale image.
    pub image: GrayImage,
}

/// An opened dataset: its frame index, camera and optional ground truth.
#[derive(Debug, Clone)]
pub struct Dataset {
    /// The folder it was opened from.
    pub root: PathBuf,
    /// Its layout.
    pub layout: Layout,
    /// The camera, with the image size of the frames.
    pub camera: Camera,
    /// Frame times and image files, in file order.
    entries: Vec<(f64, PathBuf)>,
    /// Ground-truth camera trajectory (world_from_cam), when the dataset has one.
    pub groundtruth: Option<Trajectory>,
}

impl Dataset {
    /// Open a dataset folder, detecting its layout.
    pub fn open(path: &Path) -> Result<Self, DatasetError> {
        if path.join("rgb.txt").is_file() {
            return Self::open_tum(path);
        }
        for cam_dir in [
            path.join("mav0").join("cam0"),
            path.join("cam0"),
            path.to_path_buf(),
        ] {
            if cam_dir.join("data.csv").is_file() && cam_dir.join("sensor.yaml").is_file() {
                return Self::open_euroc(path, &cam_dir);
            }
        }
        if !path.exists() {
            return Err(DatasetError::Io {
                path: path.to_owned(),
                source: std::io::Error::new(std::io::ErrorKind::NotFound, "no such folder"),
            });
        }
        Err(DatasetError::UnknownLayout {
            path: path.to_owned(),
        })
    }

    fn open_tum(root: &Path) -> Result<Self, DatasetError> {
        let index = root.join("rgb.txt");
        let text = read_text(&index)?;
        let mut entries = Vec::new();
        for (i, raw) in text.lines().enumerate() {
            let line = strip_comment(raw);
            if line.is_empty() {
                continue;
            }
            let mut it = line.split_whitespace();
            let (Some(ts), Some(file), None) = (it.next(), it.next(), it.next()) else {
                return Err(parse_err(&index, i + 1, "expected `timestamp file`"));
            };
            let t = parse_time(ts)
                .ok_or_else(|| parse_err(&index, i + 1, &format!("`{ts}` is not a timestamp")))?;
            entries.push((t, root.join(file)));
        }
        if entries.is_empty() {
            return Err(DatasetError::Empty { path: index });
        }
        let calib = root.join("calib.txt");
        if !calib.is_file() {
            return Err(DatasetError::Io {
                path: calib,
                source: std::io::Error::new(std::io::ErrorKind::NotFound, "calibration missing"),
            });
        }
        let (w, h) = image_size(&entries[0].1)?;
        let mut camera = Camera::from_calib_file(&calib, w, h)?;
        if let Some(readout_s) = read_readout(&root.join("exposures.txt"))? {
            camera.readout_s = readout_s;
            camera.validate()?;
        }
        let gt_path = root.join("groundtruth.txt");
        let groundtruth = if gt_path.is_file() {
            Some(Trajectory::read_tum(&gt_path)?)
        } else {
            None
        };
        Ok(Dataset {
            root: root.to_owned(),
            layout: Layout::Tum,
            camera,
            entries,
            groundtruth,
        })
    }

    fn open_euroc(root: &Path, cam_dir: &Path) -> Result<Self, DatasetError> {
        let index = cam_dir.join("data.csv");
        let text = read_text(&index)?;
        let mut entries = Vec::new();
        for (i, raw) in text.lines().enumerate() {
            let line = strip_comment(raw);
            if line.is_empty() {
                continue;
            }
            let mut it = line.split(',').map(str::trim);
            let (Some(ts), Some(file), None) = (it.next(), it.next(), it.next()) else {
                return Err(parse_err(&index, i + 1, "expected `timestamp_ns,filename`"));
            };
            let ns: u64 = ts.parse().map_err(|_| {
                parse_err(&index, i + 1, &format!("`{ts}` is not a timestamp in ns"))
            })?;
            entries.push((ns as f64 * 1e-9, cam_dir.join("data").join(file)));
        }
        if entries.is_empty() {
            return Err(DatasetError::Empty { path: index });
        }
        let yaml = cam_dir.join("sensor.yaml");
        let sensor = SensorYaml::read(&yaml)?;
        let camera = Camera::new(
            sensor.resolution[0],
            sensor.resolution[1],
            sensor.intrinsics,
            sensor.distortion,
        )
        .map_err(|e| parse_err(&yaml, 1, &e.to_string()))?;
        let mav0 = cam_dir.parent().unwrap_or(root);
        let gt_path = mav0.join("state_groundtruth_estimate0").join("data.csv");
        let groundtruth = if gt_path.is_file() {
            Some(read_euroc_groundtruth(&gt_path, &sensor.body_from_cam)?)
        } else {
            None
        };
        Ok(Dataset {
            root: root.to_owned(),
            layout: Layout::Euroc,
            camera,
            entries,
            groundtruth,
        })
    }

    /// Number of frames.
    pub fn len(&self) -> usize {
        self.entries.len()
    }

    /// True when the dataset has no frames (never, for an opened dataset).
    pub fn is_empty(&self) -> bool {
        self.entries.is_empty()
    }

    /// Capture time of frame `index`, seconds.
    pub fn timestamp(&self, index: usize) -> Option<f64> {
        self.entries.get(index).map(|e| e.0)
    }

    /// Image file of frame `index`.
    pub fn image_path(&self, index: usize) -> Option<&Path> {
        self.entries.get(index).map(|e| e.1.as_path())
    }

    /// Read and decode frame `index` as grayscale.
    pub fn frame(&self, index: usize) -> Result<Frame, DatasetError> {
        let (timestamp, path) = self.entries.get(index).ok_or(DatasetError::OutOfRange {
            index,
            len: self.entries.len(),
        })?;
        let image = load_gray(path)?;
        if image.width() != self.camera.width || image.height() != self.camera.height {
            return Err(DatasetError::ImageSize {
                path: path.clone(),
                found_w: image.width(),
                found_h: image.height(),
                expected_w: self.camera.width,
                expected_h: self.camera.height,
            });
        }
        Ok(Frame {
            index,
            timestamp: *timestamp,
            image,
        })
    }

    /// All frames in order; each item is a frame or the error that stopped it.
    pub fn frames(&self) -> impl Iterator<Item = Result<Frame, DatasetError>> + '_ {
        (0..self.len()).map(move |i| self.frame(i))
    }
}

/// Decode an image file to 8-bit grayscale.
pub fn load_gray(path: &Path) -> Result<GrayImage, DatasetError> {
    let bytes = std::fs::read(path).map_err(|source| DatasetError::Io {
        path: path.to_owned(),
        source,
    })?;
    let img = image::load_from_memory(&bytes).map_err(|e| DatasetError::Image {
        path: path.to_owned(),
        reason: e.to_string(),
    })?;
    Ok(img.into_luma8())
}

fn image_size(path: &Path) -> Result<(u32, u32), DatasetError> {
    image::image_dimensions(path).map_err(|e| match e {
        image::ImageError::IoError(source) => DatasetError::Io {
            path: path.to_owned(),
            source,
        },
        other => DatasetError::Image {
            path: path.to_owned(),
            reason: other.to_string(),
        },
    })
}

/// The rolling-shutter readout of a dataset's `exposures.txt` (what
/// `shotpilot-sim render` writes: `timestamp exposure_s gain readout_s ...`
/// per frame), the median over its frames; `None` without the file.
fn read_readout(path: &Path) -> Result<Option<f64>, DatasetError> {
    if !path.is_file() {
        return Ok(None);
    }
    let text = read_text(path)?;
    let mut readouts = Vec::new();
    for (i, raw) in text.lines().enumerate() {
        let line = strip_comment(raw);
        if line.is_empty() {
            continue;
        }
        let r = line
            .split_whitespace()
            .nth(3)
            .and_then(|v| v.parse::<f64>().ok())
            .filter(|r| r.is_finite() && *r >= 0.0)
            .ok_or_else(|| {
                parse_err(
                    path,
                    i + 1,
                    "expected `timestamp exposure_s gain readout_s ...` with a readout >= 0",
                )
            })?;
        readouts.push(r);
    }
    Ok(crate::stats::median(&readouts))
}

fn read_text(path: &Path) -> Result<String, DatasetError> {
    std::fs::read_to_string(path).map_err(|source| DatasetError::Io {
        path: path.to_owned(),
        source,
    })
}

fn strip_comment(line: &str) -> &str {
    line.split('#').next().unwrap_or("").trim()
}

fn parse_err(path: &Path, line: usize, reason: &str) -> DatasetError {
    DatasetError::Parse {
        path: path.to_owned(),
        line,
        reason: reason.to_owned(),
    }
}

fn parse_time(s: &str) -> Option<f64> {
    s.parse::<f64>().ok().filter(|t| t.is_finite())
}

/// The fields of a EuRoC `sensor.yaml` the reader needs.
struct SensorYaml {
    resolution: [u32; 2],
    intrinsics: [f64; 4],
    distortion: Distortion,
    body_from_cam: Isometry3<f64>,
}

impl SensorYaml {
    /// Read the flow-sequence values `resolution`, `intrinsics`,
    /// `distortion_coefficients` and `T_BS.data` (which may span lines).
    fn read(path: &Path) -> Result<Self, DatasetError> {
        let text = read_text(path)?;
        let lines: Vec<&str> = text.lines().collect();
        let find = |key: &str| -> Result<(usize, Vec<f64>), DatasetError> {
            let mut in_tbs = false;
            for (i, raw) in lines.iter().enumerate() {
                let line = strip_comment(raw);
                if line.starts_with("T_BS:") {
                    in_tbs = true;
                    continue;
                }
                if !raw.starts_with(' ') && !raw.starts_with('\t') && !line.is_empty() {
                    in_tbs = false;
                }
                let want_nested = key == "data";
                if want_nested != in_tbs {
                    continue;
                }
                let Some(rest) = line
                    .strip_prefix(key)
                    .and_then(|r| r.trim().strip_prefix(':'))
                else {
                    continue;
                };
                // Gather the bracketed list, possibly over several lines.
                let mut buf = rest.trim().to_owned();
                let mut j = i;
                while !buf.contains(']') {
                    j += 1;
                    let Some(next) = lines.get(j) else {
                        return Err(parse_err(
                            path,
                            i + 1,
                            &format!("`{key}` list is not closed"),
                        ));
                    };
                    buf.push(' ');
                    buf.push_str(strip_comment(next));
                }
                let inner = buf
                    .trim()
                    .strip_prefix('[')
                    .and_then(|b| b.split(']').next())
                    .ok_or_else(|| parse_err(path, i + 1, &format!("`{key}` is not a [list]")))?;
                let mut vals = Vec::new();
                for tok in inner.split(',').map(str::trim).filter(|t| !t.is_empty()) {
                    vals.push(tok.parse::<f64>().map_err(|_| {
                        parse_err(path, i + 1, &format!("`{tok}` in `{key}` is not a number"))
                    })?);
                }
                return Ok((i + 1, vals));
            }
            Err(parse_err(
                path,
                lines.len().max(1),
                &format!("key `{key}` not found"),
            ))
        };
        let (l, res) = find("resolution")?;
        let [w, h] = res[..] else {
            return Err(parse_err(path, l, "`resolution` needs 2 numbers"));
        };
        let (l, intr) = find("intrinsics")?;
        let [fx, fy, cx, cy] = intr[..] else {
            return Err(parse_err(path, l, "`intrinsics` needs 4 numbers"));
        };
        let (l, dist) = find("distortion_coefficients")?;
        if dist.len() < 4 || dist.len() > 5 {
            return Err(parse_err(
                path,
                l,
                "`distortion_coefficients` needs 4 or 5 numbers",
            ));
        }
        let distortion = Distortion {
            k1: dist[0],
            k2: dist[1],
            p1: dist[2],
            p2: dist[3],
            k3: dist.get(4).copied().unwrap_or(0.0),
        };
        let (l, t) = find("data")?;
        if t.len() != 16 {
            return Err(parse_err(path, l, "`T_BS.data` needs 16 numbers"));
        }
        let m = Matrix4::from_row_slice(&t);
        let r: Matrix3<f64> = m.fixed_view::<3, 3>(0, 0).into_owned();
        // The nearest rotation (polar decomposition by SVD): the file's
        // digits leave it a little off orthonormal, and an iterative fit
        // from the identity would stall on a half-turn mount.
        let svd = r.svd(true, true);
        let (Some(u), Some(v_t)) = (svd.u, svd.v_t) else {
            return Err(parse_err(path, l, "`T_BS` has no rotation part"));
        };
        let nearest = u * v_t;
        let (det, off) = (nearest.determinant(), (nearest - r).norm());
        let rigid = det.is_finite() && det > 0.5 && off.is_finite() && off <= 1e-3;
        if !rigid {
            return Err(parse_err(path, l, "`T_BS` is not a rigid transform"));
        }
        let rot = UnitQuaternion::from_rotation_matrix(&Rotation3::from_matrix_unchecked(nearest));
        let body_from_cam =
            Isometry3::from_parts(Translation3::new(m[(0, 3)], m[(1, 3)], m[(2, 3)]), rot);
        if w < 1.0 || h < 1.0 || w.fract() != 0.0 || h.fract() != 0.0 {
            return Err(parse_err(path, l, "`resolution` must be positive integers"));
        }
        Ok(SensorYaml {
            resolution: [w as u32, h as u32],
            intrinsics: [fx, fy, cx, cy],
            distortion,
            body_from_cam,
        })
    }
}

/// EuRoC ground truth: `timestamp_ns, px, py, pz, qw, qx, qy, qz, ...` (body
/// poses), turned into camera poses world_from_cam = world_from_body * body_from_cam.
fn read_euroc_groundtruth(
    path: &Path,
    body_from_cam: &Isometry3<f64>,
) -> Result<Trajectory, DatasetError> {
    let text = read_text(path)?;
    let mut poses = Vec::new();
    for (i, raw) in text.lines().enumerate() {
        let line = strip_comment(raw);
        if line.is_empty() {
            continue;
        }
        let vals: Result<Vec<f64>, _> = line.split(',').map(|t| t.trim().parse::<f64>()).collect();
        let vals = vals.map_err(|_| parse_err(path, i + 1, "expected comma-separated numbers"))?;
        if vals.len() < 8 {
            return Err(parse_err(
                path,
                i + 1,
                "expected at least 8 columns (t, p xyz, q wxyz)",
            ));
        }
        let q = Quaternion::new(vals[4], vals[5], vals[6], vals[7]);
        if q.norm() < 1e-9 {
            return Err(parse_err(path, i + 1, "zero quaternion"));
        }
        let world_from_body = Isometry3::from_parts(
            Translation3::new(vals[1], vals[2], vals[3]),
            UnitQuaternion::from_quaternion(q),
        );
        poses.push(StampedPose {
            t: vals[0] * 1e-9,
            world_from_cam: world_from_body * body_from_cam,
        });
    }
    Ok(Trajectory { poses })
}

#[cfg(test)]
mod tests {
    use super::*;

    fn write(p: &Path, s: &str) {
        std::fs::create_dir_all(p.parent().unwrap()).unwrap();
        std::fs::write(p, s).unwrap();
    }

    fn tiny_png(p: &Path, w: u32, h: u32) {
        std::fs::create_dir_all(p.parent().unwrap()).unwrap();
        GrayImage::from_fn(w, h, |x, y| image::Luma([((x * 7 + y * 3) % 251) as u8]))
            .save(p)
            .unwrap();
    }

    #[test]
    fn tum_malformed_line_names_file_and_line() {
        let d = tempfile::tempdir().unwrap();
        tiny_png(&d.path().join("rgb/a.png"), 8, 6);
        write(&d.path().join("calib.txt"), "100 100 4 3 0 0 0 0 0\n");
        write(
            &d.path().join("rgb.txt"),
            "# header\n1.0 rgb/a.png\nnot-a-time rgb/a.png\n",
        );
        let e = Dataset::open(d.path()).unwrap_err().to_string();
        assert!(e.contains("rgb.txt:3") && e.contains("not-a-time"), "{e}");
    }

    #[test]
    fn euroc_layout_reads_with_transform() {
        let d = tempfile::tempdir().unwrap();
        let cam0 = d.path().join("mav0/cam0");
        tiny_png(&cam0.join("data/100.png"), 8, 6);
        tiny_png(&cam0.join("data/200.png"), 8, 6);
        write(
            &cam0.join("data.csv"),
            "#timestamp [ns],filename\n100,100.png\n200,200.png\n",
        );
        write(
            &cam0.join("sensor.yaml"),
            "%YAML:1.0\nT_BS:\n  cols: 4\n  rows: 4\n  data: [0.0, -1.0, 0.0, 0.5,\n         1.0, 0.0, 0.0, 0.0,\n  0.0, 0.0, 1.0, 0.0,\n  0.0, 0.0, 0.0, 1.0]\nrate_hz: 20\nresolution: [8, 6]\nintrinsics: [10.0, 11.0, 4.0, 3.0]\ndistortion_coefficients: [-0.1, 0.01, 0.001, 0.002]\n",
        );
        write(
            &d.path().join("mav0/state_groundtruth_estimate0/data.csv"),
            "#t,px,py,pz,qw,qx,qy,qz\n100,1,2,3,1,0,0,0\n",
        );
        let ds = Dataset::open(d.path()).unwrap();
        assert_eq!(ds.layout, Layout::Euroc);
        assert_eq!(ds.len(), 2);
        assert!((ds.timestamp(1).unwrap() - 200e-9).abs() < 1e-15);
        assert_eq!(ds.camera.fy, 11.0);
        assert_eq!(ds.camera.distortion.p2, 0.002);
        let f = ds.frame(1).unwrap();
        assert_eq!(f.image.dimensions(), (8, 6));
        let gt = ds.groundtruth.unwrap();
        let t = gt.poses[0].world_from_cam.translation.vector;
        assert!(
            (t - nalgebra::Vector3::new(1.5, 2.0, 3.0)).norm() < 1e-12,
            "{t}"
        );
        // A malformed csv line names file and line.
        write(&cam0.join("data.csv"), "#h\n100,100.png\nabc,200.png\n");
        let e = Dataset::open(d.path()).unwrap_err().to_string();
        assert!(e.contains("data.csv:3"), "{e}");
        write(&cam0.join("data.csv"), "#h\n100,100.png\n200,200.png\n");
        let yaml = |data: &str| {
            format!(
                "%YAML:1.0\nT_BS:\n  cols: 4\n  rows: 4\n  data: [{data}]\nrate_hz: 20\nresolution: [8, 6]\nintrinsics: [10.0, 11.0, 4.0, 3.0]\ndistortion_coefficients: [-0.1, 0.01, 0.001, 0.002]\n"
            )
        };
        // A camera mounted upside down (a half-turn about the optical
        // axis): the ground truth's camera x axis is the body's -x.
        write(
            &cam0.join("sensor.yaml"),
            &yaml("-1, 0, 0, 0, 0, -1, 0, 0, 0, 0, 1, 0, 0, 0, 0, 1"),
        );
        let gt = Dataset::open(d.path()).unwrap().groundtruth.unwrap();
        let x = gt.poses[0].world_from_cam.rotation * nalgebra::Vector3::x();
        assert!((x + nalgebra::Vector3::x()).norm() < 1e-12, "{x}");
        // A scaled or sheared T_BS is not a camera mount: refused.
        write(
            &cam0.join("sensor.yaml"),
            &yaml("2, 0, 0, 0, 0, 2, 0, 0, 0, 0, 2, 0, 0, 0, 0, 1"),
        );
        let e = Dataset::open(d.path()).unwrap_err().to_string();
        assert!(e.contains("not a rigid transform"), "{e}");
    }

    #[test]
    fn undecodable_image_is_an_error_naming_it() {
        let d = tempfile::tempdir().unwrap();
        tiny_png(&d.path().join("rgb/a.png"), 8, 6);
        write(&d.path().join("rgb/b.png"), "not an image");
        write(&d.path().join("calib.txt"), "100 100 4 3\n");
        write(&d.path().join("rgb.txt"), "1.0 rgb/a.png\n2.0 rgb/b.png\n");
        let ds = Dataset::open(d.path()).unwrap();
        assert!(ds.frame(0).is_ok());
        let e = ds.frame(1).unwrap_err().to_string();
        assert!(e.contains("b.png"), "{e}");
    }
}
