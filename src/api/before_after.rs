//! The before/after picture of a refined shot, composed server-side: the
//! desired picture, the achieved live frame with the desired picture's
//! outline (the shot error's homography), and the two blended half and
//! half, side by side under a line of text with the round and the shot
//! error (a built-in 3x5 pixel font, drawn 3 times larger).

use image::{GrayImage, Rgb, RgbImage, imageops};

use super::events::Achieved;

/// Height of the text band, pixels.
const BAND: u32 = 27;
/// Gap between the panels, pixels.
const GAP: u32 = 8;
/// Font scale.
const SCALE: u32 = 3;

/// 3x5 glyphs, rows top to bottom, 3 bits each (bit 2 = left column).
fn glyph(c: char) -> Option<[u8; 5]> {
    Some(match c.to_ascii_uppercase() {
        '0' => [7, 5, 5, 5, 7],
        '1' => [2, 6, 2, 2, 7],
        '2' => [7, 1, 7, 4, 7],
        '3' => [7, 1, 7, 1, 7],
        '4' => [5, 5, 7, 1, 1],
        '5' => [7, 4, 7, 1, 7],
        '6' => [7, 4, 7, 5, 7],
        '7' => [7, 1, 1, 1, 1],
        '8' => [7, 5, 7, 5, 7],
        '9' => [7, 5, 7, 1, 7],
        '.' => [0, 0, 0, 0, 2],
        ':' => [0, 2, 0, 2, 0],
        '-' => [0, 0, 7, 0, 0],
        '%' => [5, 1, 2, 4, 5],
        '/' => [1, 1, 2, 4, 4],
        ' ' => [0, 0, 0, 0, 0],
        'A' => [2, 5, 7, 5, 5],
        'C' => [7, 4, 4, 4, 7],
        'D' => [6, 5, 5, 5, 6],
        'E' => [7, 4, 6, 4, 7],
        'F' => [7, 4, 6, 4, 4],
        'H' => [5, 5, 7, 5, 5],
        'I' => [7, 2, 2, 2, 7],
        'L' => [4, 4, 4, 4, 7],
        'N' => [6, 5, 5, 5, 5],
        'O' => [7, 5, 5, 5, 7],
        'R' => [6, 5, 6, 5, 5],
        'S' => [7, 4, 7, 1, 7],
        'T' => [7, 2, 2, 2, 2],
        'U' => [5, 5, 5, 5, 7],
        'V' => [5, 5, 5, 5, 2],
        'Y' => [5, 5, 2, 2, 2],
        _ => return None,
    })
}

/// Draws `text` with its top-left corner at (x, y); unknown characters
/// are left blank.
fn text(img: &mut RgbImage, x: u32, y: u32, s: &str, color: Rgb<u8>) {
    for (i, c) in s.chars().enumerate() {
        let Some(g) = glyph(c) else { continue };
        let x0 = x + i as u32 * 4 * SCALE;
        for (row, bits) in g.iter().enumerate() {
            for col in 0..3u32 {
                if bits & (4 >> col) == 0 {
                    continue;
                }
                for dy in 0..SCALE {
                    for dx in 0..SCALE {
                        let (px, py) = (x0 + col * SCALE + dx, y + row as u32 * SCALE + dy);
                        if px < img.width() && py < img.height() {
                            img.put_pixel(px, py, color);
                        }
                    }
                }
            }
        }
    }
}

/// A 2-pixel line from `a` to `b` (offset by `(ox, oy)`), clipped to the
/// panel `[ox, ox + w) x [oy, oy + h)`.
fn line(img: &mut RgbImage, a: [f64; 2], b: [f64; 2], panel: (u32, u32, u32, u32), c: Rgb<u8>) {
    let (ox, oy, w, h) = panel;
    let n = ((b[0] - a[0]).hypot(b[1] - a[1]).ceil() as usize).clamp(1, 20_000);
    for i in 0..=n {
        let t = i as f64 / n as f64;
        let (x, y) = (a[0] + t * (b[0] - a[0]), a[1] + t * (b[1] - a[1]));
        for (dx, dy) in [(0.0, 0.0), (1.0, 0.0), (0.0, 1.0)] {
            let (px, py) = ((x + dx).round(), (y + dy).round());
            if px >= 0.0 && py >= 0.0 && px < f64::from(w) && py < f64::from(h) {
                img.put_pixel(ox + px as u32, oy + py as u32, c);
            }
        }
    }
}

/// The before/after picture (see the module's documentation). The desired
/// picture is scaled to the live frame's size when they differ.
pub fn compose_before_after(desired: &GrayImage, achieved: &Achieved) -> RgbImage {
    let live = &*achieved.frame;
    let (w, h) = live.dimensions();
    let desired = if desired.dimensions() == (w, h) {
        desired.clone()
    } else {
        imageops::resize(desired, w, h, imageops::FilterType::Triangle)
    };
    let mut out = RgbImage::from_pixel(3 * w + 2 * GAP, h + BAND, Rgb([24, 27, 32]));
    let grey = |v: u8| Rgb([v, v, v]);
    for y in 0..h {
        for x in 0..w {
            let (d, l) = (desired.get_pixel(x, y)[0], live.get_pixel(x, y)[0]);
            out.put_pixel(x, BAND + y, grey(d));
            out.put_pixel(w + GAP + x, BAND + y, grey(l));
            let mix = ((u16::from(d) + u16::from(l)) / 2) as u8;
            out.put_pixel(2 * (w + GAP) + x, BAND + y, grey(mix));
        }
    }
    let outline = Rgb([255, 80, 80]);
    if let Some(c) = achieved.corners_px {
        for panel in [1, 2] {
            let p = (panel * (w + GAP), BAND, w, h);
            for (i, a) in c.iter().enumerate() {
                line(&mut out, *a, c[(i + 1) % 4], p, outline);
            }
        }
    }
    let white = Rgb([230, 230, 230]);
    text(&mut out, 6, 6, "DESIRED", white);
    let err = achieved
        .shot_error_pct
        .map_or("NONE".to_owned(), |e| format!("{e:.2} %"));
    text(
        &mut out,
        w + GAP + 6,
        6,
        &format!("ACHIEVED ROUND {}: ERROR {err}", achieved.round),
        white,
    );
    text(&mut out, 2 * (w + GAP) + 6, 6, "OVERLAY", white);
    out
}

#[cfg(test)]
mod tests {
    use super::*;
    use std::sync::Arc;

    #[test]
    fn panels_outline_and_text_land_where_they_should() {
        let desired = GrayImage::from_pixel(64, 48, image::Luma([200]));
        let live = GrayImage::from_pixel(64, 48, image::Luma([100]));
        let a = Achieved {
            frame: Arc::new(live),
            round: 1,
            shot_error_pct: Some(0.84),
            corners_px: Some([[10.0, 10.0], [50.0, 10.0], [50.0, 40.0], [10.0, 40.0]]),
        };
        let img = compose_before_after(&desired, &a);
        assert_eq!(img.dimensions(), (3 * 64 + 2 * GAP, 48 + BAND));
        // Desired, live and the blend, away from the outline.
        assert_eq!(img.get_pixel(30, BAND + 25)[0], 200);
        assert_eq!(img.get_pixel(64 + GAP + 30, BAND + 25)[0], 100);
        assert_eq!(img.get_pixel(2 * (64 + GAP) + 30, BAND + 25)[0], 150);
        // The outline's top edge on the live panel and the blend.
        for panel in [1, 2] {
            let p = img.get_pixel(panel * (64 + GAP) + 30, BAND + 10);
            assert_eq!(p, &Rgb([255, 80, 80]), "panel {panel}");
        }
        // Text is drawn in the band, nothing of it below.
        let lit = (0..img.width())
            .flat_map(|x| (0..BAND).map(move |y| (x, y)))
            .filter(|&(x, y)| img.get_pixel(x, y)[0] == 230)
            .count();
        assert!(lit > 100, "{lit}");
        // A desired picture of another size is scaled to the frame's.
        let small = GrayImage::from_pixel(32, 24, image::Luma([200]));
        let img = compose_before_after(&small, &a);
        assert_eq!(img.get_pixel(30, BAND + 25)[0], 200);
    }
}
