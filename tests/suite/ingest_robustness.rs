//! Property tests of the MJPEG multipart parser and the shot request
//! parser: arbitrary bytes never panic, and any chunking of a valid stream
//! yields the same parts as feeding it whole.

use proptest::prelude::*;
use shotpilot::video::mjpeg::{ParseEvent, PartParser, jpeg_end};

fn parts_of(p: &mut PartParser) -> Vec<Vec<u8>> {
    let mut out = Vec::new();
    while let Some(ev) = p.next_part() {
        if let ParseEvent::Part(x) = ev {
            out.push(x.body);
        }
    }
    out
}

fn jpegish(tag: u8, len: usize) -> Vec<u8> {
    let mut v = vec![0xFF, 0xD8, 0xFF, 0xDA, 0x00, 0x02];
    v.extend((0..len).map(|i| (i as u8 ^ tag) & 0x7F));
    v.extend_from_slice(&[0xFF, 0xD9]);
    v
}

proptest! {
    #![proptest_config(ProptestConfig { cases: 512, ..ProptestConfig::default() })]

    #[test]
    fn arbitrary_bytes_never_panic(data in proptest::collection::vec(any::<u8>(), 0..4096), boundary in proptest::option::of("[a-z]{1,8}"), cuts in proptest::collection::vec(0usize..4096, 0..8)) {
        let mut p = PartParser::new(boundary.as_deref(), 2048);
        let mut cuts = cuts;
        cuts.sort_unstable();
        let mut last = 0;
        for c in cuts.into_iter().chain(std::iter::once(data.len())) {
            let c = c.min(data.len());
            if c < last { continue; }
            p.push(&data[last..c]);
            last = c;
            while let Some(ev) = p.next_part() {
                if let ParseEvent::Part(x) = ev {
                    prop_assert!(x.body.len() <= 4096);
                }
            }
        }
        let _ = jpeg_end(&data);
    }

    #[test]
    fn chunking_does_not_change_the_parts(lens in proptest::collection::vec(0usize..300, 1..6), with_len in any::<bool>(), lf_only in any::<bool>(), cuts in proptest::collection::vec(0usize..3000, 0..12)) {
        let eol = if lf_only { "\n" } else { "\r\n" };
        let mut stream = Vec::new();
        let mut want = Vec::new();
        for (i, &l) in lens.iter().enumerate() {
            let j = jpegish(i as u8, l);
            stream.extend_from_slice(format!("--frm{eol}Content-Type: image/jpeg{eol}").as_bytes());
            if with_len {
                stream.extend_from_slice(format!("Content-Length: {}{eol}", j.len()).as_bytes());
            }
            stream.extend_from_slice(eol.as_bytes());
            stream.extend_from_slice(&j);
            stream.extend_from_slice(eol.as_bytes());
            want.push(j);
        }
        stream.extend_from_slice(format!("--frm{eol}").as_bytes());
        let mut p = PartParser::new(Some("frm"), 1 << 20);
        let mut cuts = cuts;
        cuts.sort_unstable();
        let mut got = Vec::new();
        let mut last = 0;
        for c in cuts.into_iter().chain(std::iter::once(stream.len())) {
            let c = c.min(stream.len());
            if c < last { continue; }
            p.push(&stream[last..c]);
            last = c;
            got.extend(parts_of(&mut p));
        }
        prop_assert_eq!(got, want);
    }

    #[test]
    fn shot_request_parser_never_panics(data in proptest::collection::vec(any::<u8>(), 0..512)) {
        let _ = shotpilot::api::parse_shot_request(&data);
    }

    #[test]
    fn shot_requests_with_other_than_four_anchors_are_refused(n in 0usize..9, kf in any::<u64>()) {
        let anchors: Vec<[f64; 2]> = (0..n).map(|i| [i as f64 * 10.0, 5.0]).collect();
        let body = serde_json::json!({"keyframe_id": kf, "anchors": anchors}).to_string();
        let r = shotpilot::api::parse_shot_request(body.as_bytes());
        if n == 4 {
            prop_assert!(r.is_ok());
        } else {
            let e = r.unwrap_err();
            prop_assert_eq!(e.status().as_u16(), 400);
            prop_assert_eq!(e.code(), "bad_anchors");
        }
    }
}
