//! Vocabulary files: the native binary format and DBoW2's text format.
//!
//! # Native format (version 1), all little-endian
//!
//! | offset | size | field |
//! |---|---|---|
//! | 0 | 8 | magic `SPBOWVOC` |
//! | 8 | 4 | format version (1) |
//! | 12 | 4 | branching factor `k` |
//! | 16 | 4 | levels `L` |
//! | 20 | 1 | weighting (DBoW2 code) |
//! | 21 | 1 | scoring (DBoW2 code) |
//! | 22 | 2 | reserved, 0 |
//! | 24 | 4 | node count `n` (root included) |
//! | 28 | 4 | word count `w` |
//! | 32 | 32 n | node centroids, four `u64` each |
//! | | 4 n | first child of each node (`u32`) |
//! | | n | child count of each node (`u8`) |
//! | | 4 w | node of each word (`u32`) |
//! | | 4 w | weight of each word (`f32`) |
//! | end - 8 | 8 | checksum of all bytes before it (see [`checksum`]) |
//!
//! # DBoW2 text format (ORB-SLAM's `ORBvoc.txt`)
//!
//! The first line is `k L scoring weighting`; then one line per node but the
//! root, node `i` (1-based) on line `i + 1`: `parent_id is_leaf d0 .. d31
//! weight`, with the 32 descriptor bytes as decimal numbers. Word ids are
//! given to the leaves in file order, as DBoW2 does, so imported BoW vectors
//! use ORB-SLAM's word ids. Node ids are renumbered breadth first (children
//! contiguous); feature-vector node ids are therefore this module's own.

use std::path::Path;

use super::vocabulary::{Parts, Scoring, Vocabulary, Weighting};
use super::{BowError, Descriptor};

/// First bytes of a native vocabulary file.
pub const FILE_MAGIC: [u8; 8] = *b"SPBOWVOC";
/// Version of the native format this build writes and reads.
pub const FILE_VERSION: u32 = 1;
const HEADER_LEN: usize = 32;
const CHECKSUM_LEN: usize = 8;

impl Vocabulary {
    /// Serialise into the native binary format.
    pub fn to_bytes(&self) -> Vec<u8> {
        let n = self.node_count();
        let w = self.word_count();
        let mut out = Vec::with_capacity(HEADER_LEN + 37 * n + 8 * w + CHECKSUM_LEN);
        out.extend_from_slice(&FILE_MAGIC);
        out.extend_from_slice(&FILE_VERSION.to_le_bytes());
        out.extend_from_slice(&self.k.to_le_bytes());
        out.extend_from_slice(&self.levels.to_le_bytes());
        out.push(self.weighting.code() as u8);
        out.push(self.scoring.code() as u8);
        out.extend_from_slice(&[0, 0]);
        out.extend_from_slice(&(n as u32).to_le_bytes());
        out.extend_from_slice(&(w as u32).to_le_bytes());
        for d in &self.descriptors {
            for x in d {
                out.extend_from_slice(&x.to_le_bytes());
            }
        }
        for x in &self.first_child {
            out.extend_from_slice(&x.to_le_bytes());
        }
        out.extend_from_slice(&self.child_count);
        for x in &self.word_node {
            out.extend_from_slice(&x.to_le_bytes());
        }
        for x in &self.word_weight {
            out.extend_from_slice(&x.to_le_bytes());
        }
        let sum = checksum(&out);
        out.extend_from_slice(&sum.to_le_bytes());
        out
    }

    /// Parse the native binary format, checking magic, version, length,
    /// checksum and tree structure.
    pub fn from_bytes(bytes: &[u8]) -> Result<Vocabulary, BowError> {
        if bytes.len() < 8 || bytes[..8] != FILE_MAGIC {
            let mut found = [0u8; 8];
            let m = bytes.len().min(8);
            found[..m].copy_from_slice(&bytes[..m]);
            if bytes.len() < 8 && FILE_MAGIC.starts_with(&bytes[..m]) {
                return Err(BowError::Truncated {
                    needed: (HEADER_LEN + CHECKSUM_LEN) as u64,
                    found: bytes.len() as u64,
                });
            }
            return Err(BowError::BadMagic {
                found,
                expected: FILE_MAGIC,
            });
        }
        if bytes.len() < HEADER_LEN + CHECKSUM_LEN {
            return Err(BowError::Truncated {
                needed: (HEADER_LEN + CHECKSUM_LEN) as u64,
                found: bytes.len() as u64,
            });
        }
        let u32_at =
            |o: usize| u32::from_le_bytes([bytes[o], bytes[o + 1], bytes[o + 2], bytes[o + 3]]);
        let version = u32_at(8);
        if version != FILE_VERSION {
            return Err(BowError::UnsupportedVersion {
                found: version,
                supported: FILE_VERSION,
            });
        }
        let k = u32_at(12);
        let levels = u32_at(16);
        let weighting_code = u32::from(bytes[20]);
        let scoring_code = u32::from(bytes[21]);
        let n = u32_at(24) as u64;
        let w = u32_at(28) as u64;
        let needed = (HEADER_LEN + CHECKSUM_LEN) as u64 + 37 * n + 8 * w;
        let found = bytes.len() as u64;
        if found < needed {
            return Err(BowError::Truncated { needed, found });
        }
        if found > needed {
            return Err(BowError::TrailingBytes {
                extra: found - needed,
            });
        }
        let body_len = bytes.len() - CHECKSUM_LEN;
        let mut stored = [0u8; 8];
        stored.copy_from_slice(&bytes[body_len..]);
        let stored = u64::from_le_bytes(stored);
        let computed = checksum(&bytes[..body_len]);
        if stored != computed {
            return Err(BowError::ChecksumMismatch { stored, computed });
        }
        let weighting = Weighting::from_code(weighting_code)?;
        let scoring = Scoring::from_code(scoring_code)?;

        let (n, w) = (n as usize, w as usize);
        let mut at = HEADER_LEN;
        let descriptors: Vec<Descriptor> = bytes[at..at + 32 * n]
            .chunks_exact(32)
            .map(|c| {
                let mut d = [0u64; 4];
                for (x, b) in d.iter_mut().zip(c.chunks_exact(8)) {
                    *x = u64_le(b);
                }
                d
            })
            .collect();
        at += 32 * n;
        let first_child: Vec<u32> = bytes[at..at + 4 * n].chunks_exact(4).map(u32_le).collect();
        at += 4 * n;
        let child_count: Vec<u8> = bytes[at..at + n].to_vec();
        at += n;
        let word_node: Vec<u32> = bytes[at..at + 4 * w].chunks_exact(4).map(u32_le).collect();
        at += 4 * w;
        let word_weight: Vec<f32> = bytes[at..at + 4 * w]
            .chunks_exact(4)
            .map(|c| f32::from_bits(u32_le(c)))
            .collect();
        Vocabulary::from_parts(Parts {
            k,
            levels,
            weighting,
            scoring,
            descriptors,
            first_child,
            child_count,
            word_node,
            word_weight,
        })
    }

    /// Write the native binary format to `path`.
    pub fn save(&self, path: &Path) -> Result<(), BowError> {
        std::fs::write(path, self.to_bytes()).map_err(|source| BowError::Io {
            path: path.to_path_buf(),
            source,
        })
    }

    /// Read a native binary vocabulary file.
    pub fn load(path: &Path) -> Result<Vocabulary, BowError> {
        let bytes = std::fs::read(path).map_err(|source| BowError::Io {
            path: path.to_path_buf(),
            source,
        })?;
        Vocabulary::from_bytes(&bytes)
    }

    /// Read a DBoW2 text vocabulary (ORB-SLAM's `ORBvoc.txt`) from `path`.
    pub fn import_dbow2_text(path: &Path) -> Result<Vocabulary, BowError> {
        let bytes = std::fs::read(path).map_err(|source| BowError::Io {
            path: path.to_path_buf(),
            source,
        })?;
        Vocabulary::from_dbow2_text(&bytes)
    }

    /// Parse a DBoW2 text vocabulary held in memory.
    pub fn from_dbow2_text(text: &[u8]) -> Result<Vocabulary, BowError> {
        let mut lines = text
            .split(|&b| b == b'\n')
            .enumerate()
            .map(|(i, l)| (i + 1, l))
            .filter(|(_, l)| l.iter().any(|b| !b.is_ascii_whitespace()));
        let (header_line, header) = lines.next().ok_or(BowError::TextFormat {
            line: 1,
            reason: "empty file".into(),
        })?;
        let fields: Vec<&[u8]> = tokens(header).collect();
        if fields.len() != 4 {
            return Err(BowError::TextFormat {
                line: header_line,
                reason: format!(
                    "header must be `k L scoring weighting`, found {} fields",
                    fields.len()
                ),
            });
        }
        let hdr = |i: usize, name: &str, lo: u32, hi: u32| {
            parse_u32(fields[i])
                .filter(|v| (lo..=hi).contains(v))
                .ok_or_else(|| BowError::TextFormat {
                    line: header_line,
                    reason: format!("{name} must be an integer in {lo}..={hi}"),
                })
        };
        let k = hdr(0, "k", 2, 255)?;
        let levels = hdr(1, "L", 1, 16)?;
        let scoring = Scoring::from_code(hdr(2, "scoring", 0, 5)?)?;
        let weighting = Weighting::from_code(hdr(3, "weighting", 0, 3)?)?;

        // Nodes in file order; index 0 is the root.
        let mut parent: Vec<u32> = vec![u32::MAX];
        let mut is_leaf: Vec<bool> = vec![false];
        let mut descriptors: Vec<Descriptor> = vec![[0; 4]];
        let mut weight: Vec<f32> = vec![0.0];
        let mut line_of: Vec<usize> = vec![header_line];
        for (line, l) in lines {
            let bad = |reason: String| BowError::TextFormat { line, reason };
            let id = parent.len() as u64;
            if id >= u64::from(u32::MAX) {
                return Err(bad("too many nodes".into()));
            }
            let mut t = tokens(l);
            let p = t
                .next()
                .and_then(parse_u32)
                .ok_or_else(|| bad("parent id must be an integer".into()))?;
            if u64::from(p) >= id {
                return Err(bad(format!(
                    "parent {p} of node {id} is not an earlier node"
                )));
            }
            let leaf = match t.next() {
                Some(b"0") => false,
                Some(b"1") => true,
                _ => return Err(bad("is_leaf must be 0 or 1".into())),
            };
            let mut bytes = [0u8; 32];
            for (j, b) in bytes.iter_mut().enumerate() {
                *b = t
                    .next()
                    .and_then(parse_u32)
                    .filter(|&v| v <= 255)
                    .ok_or_else(|| {
                        bad(format!("descriptor byte {j} must be an integer in 0..=255"))
                    })? as u8;
            }
            let wt = t
                .next()
                .and_then(|s| std::str::from_utf8(s).ok())
                .and_then(|s| s.parse::<f64>().ok())
                .filter(|x| x.is_finite() && *x >= 0.0)
                .ok_or_else(|| bad("weight must be a finite non-negative number".into()))?;
            if t.next().is_some() {
                return Err(bad("more than 35 fields".into()));
            }
            let mut d = [0u64; 4];
            for (x, c) in d.iter_mut().zip(bytes.chunks_exact(8)) {
                *x = u64_le(c);
            }
            parent.push(p);
            is_leaf.push(leaf);
            descriptors.push(d);
            weight.push(wt as f32);
            line_of.push(line);
        }
        let n = parent.len();
        if n < 2 {
            return Err(BowError::TextFormat {
                line: header_line,
                reason: "no nodes after the header".into(),
            });
        }

        // Children of each node, in file order (counting sort by parent).
        let mut start = vec![0u32; n + 1];
        for &p in &parent[1..] {
            start[p as usize + 1] += 1;
        }
        for i in 0..n {
            start[i + 1] += start[i];
        }
        let mut fill = start.clone();
        let mut children = vec![0u32; n - 1];
        for (i, &p) in parent.iter().enumerate().skip(1) {
            children[fill[p as usize] as usize] = i as u32;
            fill[p as usize] += 1;
        }
        for i in 0..n {
            let c = start[i + 1] - start[i];
            let bad = |reason: &str| BowError::TextFormat {
                line: line_of[i],
                reason: format!("node {i}: {reason}"),
            };
            if c > k {
                return Err(bad("more children than k"));
            }
            if i > 0 && is_leaf[i] && c > 0 {
                return Err(bad("marked as a leaf but has children"));
            }
            if !is_leaf[i] && c == 0 {
                return Err(bad("not marked as a leaf but has no children"));
            }
        }

        // Breadth-first renumbering: children of a node get contiguous ids.
        let mut new_of_old = vec![0u32; n];
        let mut old_of_new = Vec::with_capacity(n);
        old_of_new.push(0u32);
        let mut head = 0usize;
        while head < old_of_new.len() {
            let old = old_of_new[head] as usize;
            head += 1;
            for &c in &children[start[old] as usize..start[old + 1] as usize] {
                new_of_old[c as usize] = old_of_new.len() as u32;
                old_of_new.push(c);
            }
        }
        let mut new_descriptors = Vec::with_capacity(n);
        let mut first_child = Vec::with_capacity(n);
        let mut child_count = Vec::with_capacity(n);
        for &old in &old_of_new {
            let old = old as usize;
            new_descriptors.push(descriptors[old]);
            let (s, e) = (start[old] as usize, start[old + 1] as usize);
            child_count.push((e - s) as u8);
            first_child.push(if e > s {
                new_of_old[children[s] as usize]
            } else {
                0
            });
        }
        let mut word_node = Vec::new();
        let mut word_weight = Vec::new();
        for old in 1..n {
            if is_leaf[old] {
                word_node.push(new_of_old[old]);
                word_weight.push(weight[old]);
            }
        }
        Vocabulary::from_parts(Parts {
            k,
            levels,
            weighting,
            scoring,
            descriptors: new_descriptors,
            first_child,
            child_count,
            word_node,
            word_weight,
        })
    }
}

fn tokens(line: &[u8]) -> impl Iterator<Item = &[u8]> {
    line.split(|b| b.is_ascii_whitespace())
        .filter(|t| !t.is_empty())
}

fn parse_u32(t: &[u8]) -> Option<u32> {
    if t.is_empty() || t.len() > 10 {
        return None;
    }
    let mut v = 0u64;
    for &b in t {
        if !b.is_ascii_digit() {
            return None;
        }
        v = v * 10 + u64::from(b - b'0');
    }
    u32::try_from(v).ok()
}

fn u32_le(b: &[u8]) -> u32 {
    let mut a = [0u8; 4];
    a.copy_from_slice(&b[..4]);
    u32::from_le_bytes(a)
}

fn u64_le(b: &[u8]) -> u64 {
    let mut a = [0u8; 8];
    a.copy_from_slice(&b[..8]);
    u64::from_le_bytes(a)
}

/// The file checksum: four independent 64-bit lanes over 32-byte blocks,
/// each step `lane = rotl((lane ^ word) * P1, 31)`, a zero-padded tail block,
/// then the lanes and the length mixed into one value. Each step is a
/// bijection of the lane, so a change confined to one 8-byte word is always
/// detected.
pub fn checksum(bytes: &[u8]) -> u64 {
    const P1: u64 = 0x9E37_79B1_85EB_CA87;
    const P2: u64 = 0xC2B2_AE3D_27D4_EB4F;
    const P3: u64 = 0x1656_67B1_9E37_79F9;
    let mut lanes = [P1, P2, P3, P1 ^ P2];
    let step = |lane: u64, word: u64| (lane ^ word).wrapping_mul(P1).rotate_left(31);
    let mut blocks = bytes.chunks_exact(32);
    for b in &mut blocks {
        lanes[0] = step(lanes[0], u64_le(&b[0..8]));
        lanes[1] = step(lanes[1], u64_le(&b[8..16]));
        lanes[2] = step(lanes[2], u64_le(&b[16..24]));
        lanes[3] = step(lanes[3], u64_le(&b[24..32]));
    }
    let rest = blocks.remainder();
    if !rest.is_empty() {
        let mut tail = [0u8; 32];
        tail[..rest.len()].copy_from_slice(rest);
        for (i, lane) in lanes.iter_mut().enumerate() {
            *lane = step(*lane, u64_le(&tail[8 * i..8 * i + 8]));
        }
    }
    let mut h = (bytes.len() as u64).wrapping_mul(P3);
    for lane in lanes {
        h = (h ^ lane.wrapping_mul(P2)).rotate_left(27).wrapping_mul(P1);
    }
    h ^= h >> 33;
    h = h.wrapping_mul(P2);
    h ^= h >> 29;
    h
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::bow::{TrainParams, WordId};
    use rand::rngs::SmallRng;
    use rand::{Rng, SeedableRng};

    fn small_vocabulary() -> Vocabulary {
        let mut rng = SmallRng::seed_from_u64(9);
        let images: Vec<Vec<Descriptor>> = (0..6)
            .map(|_| (0..300).map(|_| rng.random()).collect())
            .collect();
        let params = TrainParams {
            k: 4,
            levels: 3,
            seed: 4,
            max_iterations: 10,
        };
        Vocabulary::train(&images, &params, &mut |_| {}).expect("train")
    }

    #[test]
    fn binary_round_trip_is_exact() {
        let v = small_vocabulary();
        let bytes = v.to_bytes();
        assert_eq!(bytes.len(), 40 + 37 * v.node_count() + 8 * v.word_count());
        let back = Vocabulary::from_bytes(&bytes).expect("load");
        assert_eq!(back, v);
    }

    #[test]
    fn binary_errors_are_typed() {
        let v = small_vocabulary();
        let bytes = v.to_bytes();
        let mut b = bytes.clone();
        b[0] = b'X';
        assert!(matches!(
            Vocabulary::from_bytes(&b),
            Err(BowError::BadMagic { .. })
        ));
        let mut b = bytes.clone();
        b[8] = 7;
        assert!(matches!(
            Vocabulary::from_bytes(&b),
            Err(BowError::UnsupportedVersion {
                found: 7,
                supported: 1
            })
        ));
        for cut in [0usize, 5, 20, bytes.len() / 2, bytes.len() - 1] {
            assert!(
                matches!(
                    Vocabulary::from_bytes(&bytes[..cut]),
                    Err(BowError::Truncated { .. })
                ),
                "cut at {cut}"
            );
        }
        let mut b = bytes.clone();
        b.push(0);
        assert!(matches!(
            Vocabulary::from_bytes(&b),
            Err(BowError::TrailingBytes { extra: 1 })
        ));
        // Flip one bit anywhere in the body: checksum mismatch.
        for pos in [HEADER_LEN + 3, bytes.len() / 2, bytes.len() - 9] {
            let mut b = bytes.clone();
            b[pos] ^= 0x10;
            assert!(
                matches!(
                    Vocabulary::from_bytes(&b),
                    Err(BowError::ChecksumMismatch { .. })
                ),
                "flip at {pos}"
            );
        }
    }

    #[test]
    fn checksum_detects_single_byte_changes() {
        let data: Vec<u8> = (0..100u32).map(|i| (i * 7 + 3) as u8).collect();
        let base = checksum(&data);
        for i in 0..data.len() {
            let mut d = data.clone();
            d[i] ^= 1;
            assert_ne!(checksum(&d), base, "byte {i}");
        }
        assert_ne!(checksum(&data[..99]), base);
    }

    #[test]
    fn text_import_of_hand_written_tree() {
        // k = 2, L = 2. Root children: node 1 (zeros, inner), node 2 (all
        // 0xff, leaf, word 0). Node 1 children: node 3 (zeros, word 1),
        // node 4 (byte 0 = 0x0f, word 2).
        let zeros = vec!["0"; 32].join(" ");
        let ones = vec!["255"; 32].join(" ");
        let mut low = vec!["0"; 32];
        low[0] = "15";
        let low = low.join(" ");
        let text =
            format!("2 2 0 0\n0 0 {zeros} 0\n0 1 {ones} 0.5\n1 1 {zeros} 1.25\r\n1 1 {low} 2\n\n");
        let v = Vocabulary::from_dbow2_text(text.as_bytes()).expect("import");
        assert_eq!(
            (v.branching(), v.levels(), v.word_count(), v.node_count()),
            (2, 2, 3, 5)
        );
        assert_eq!(v.word_of(&[u64::MAX; 4]), (WordId(0), 0.5));
        assert_eq!(v.word_of(&[0x1, 0, 0, 0]), (WordId(1), 1.25));
        assert_eq!(v.word_of(&[0x0e, 0, 0, 0]), (WordId(2), 2.0));
        // Byte 8 is the low byte of the second u64.
        let mut b8 = vec!["0"; 32];
        b8[8] = "15";
        let text = format!("2 1 0 0\n0 1 {zeros} 1\n0 1 {} 1\n", b8.join(" "));
        let v = Vocabulary::from_dbow2_text(text.as_bytes()).expect("import");
        assert_eq!(v.word_of(&[0, 0x0f, 0, 0]).0, WordId(1));
    }

    #[test]
    fn text_import_errors_name_the_line() {
        let zeros = vec!["0"; 32].join(" ");
        let cases = [
            ("", 1usize),
            ("10 6 0\n", 1),
            ("10 6 0 0\n0 1 1 2 3\n", 2),
            (&format!("2 1 0 0\n0 1 {zeros} 1\n5 1 {zeros} 1\n"), 3),
            (&format!("2 1 0 0\n0 1 {zeros} -1\n"), 2),
            (&format!("2 1 0 0\n0 2 {zeros} 1\n"), 2),
            (&format!("2 1 0 0\n0 0 {zeros} 1\n"), 2),
        ];
        for (text, line) in cases {
            match Vocabulary::from_dbow2_text(text.as_bytes()) {
                Err(BowError::TextFormat { line: l, .. }) => assert_eq!(l, line, "{text:?}"),
                other => panic!("{text:?}: {other:?}"),
            }
        }
        assert!(matches!(
            Vocabulary::from_dbow2_text(format!("2 1 1 0\n0 1 {zeros} 1\n").as_bytes()),
            Err(BowError::Unsupported {
                what: "scoring",
                code: 1,
                ..
            })
        ));
    }
}
