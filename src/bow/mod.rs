//! Bag of binary words: a vocabulary tree over ORB descriptors, BoW vectors,
//! and a keyframe database for place recognition.
//!
//! The design follows DBoW2 (Galvez-Lopez and Tardos, "Bags of Binary Words
//! for Fast Place Recognition in Image Sequences", T-RO 2012) as ORB-SLAM uses
//! it:
//!
//! - [`Vocabulary`]: a tree with branching factor `k` and depth `L`, built by
//!   hierarchical k-majority clustering (k-means++ seeding, Hamming distance,
//!   bitwise-majority centroids). Its leaves are the *words*; each word has a
//!   weight (TF-IDF's inverse document frequency `ln(N / n_i)` over the
//!   training images).
//! - [`BowVector`]: a descriptor set turned into a sparse, L1-normalised
//!   vector of word weights, sorted by word id. Two vectors score with
//!   DBoW2's L1 score `1 - 0.5 |v1 - v2|_1` (in `[0, 1]`, 1 for identical).
//! - [`FeatureVector`]: the *direct index*: for each vocabulary node at a
//!   chosen level, the indices of the features that went through it. Two
//!   images match features only within the same node (BoW-guided matching).
//! - [`KeyFrameDatabase`]: an inverted index word -> keyframes, queried for
//!   the most similar keyframes, and for ORB-SLAM's covisibility-grouped
//!   relocalisation / loop candidates.
//! - Storage: a compact little-endian binary file ([`Vocabulary::save`],
//!   [`Vocabulary::load`]) and import of DBoW2 text vocabularies in
//!   ORB-SLAM's `ORBvoc.txt` format ([`Vocabulary::import_dbow2_text`]).
//!
//! # Descriptor bits
//!
//! A descriptor is 256 bits as `[u64; 4]`. Byte `j` of an OpenCV / DBoW2
//! descriptor (`d0 .. d31`) is bits `8 (j % 8) ..` of word `j / 8`, i.e. each
//! `u64` is the little-endian reading of eight consecutive bytes. Hamming
//! distances do not depend on this choice, but centroids read from a DBoW2
//! file must use the same packing as the extractor.

mod database;
mod io;
mod train;
mod vector;
mod vocabulary;

pub use database::{Candidate, CandidateParams, KeyFrameDatabase, KeyFrameId, QueryResult};
pub use io::{FILE_MAGIC, FILE_VERSION, checksum};
pub use train::{TrainParams, TrainPhase, TrainProgress};
pub use vector::{BowVector, FeatureVector, NodeId, WordId};
pub use vocabulary::{Scoring, Vocabulary, Weighting};

use std::path::PathBuf;

pub(crate) use crate::features::Descriptor;

/// Hamming distance between two 256-bit descriptors; the same as
/// [`crate::features::hamming`], but always inlined so that the vocabulary's
/// popcount-enabled descent compiles it to `popcnt`.
#[inline(always)]
pub(crate) fn hamming(a: &Descriptor, b: &Descriptor) -> u32 {
    (a[0] ^ b[0]).count_ones()
        + (a[1] ^ b[1]).count_ones()
        + (a[2] ^ b[2]).count_ones()
        + (a[3] ^ b[3]).count_ones()
}

/// The tunable numbers of the BoW module that are not training parameters.
#[derive(Debug, Clone, PartialEq)]
pub struct Params {
    /// Level (counted from the root, which is level 0) of the nodes of the
    /// direct index used for BoW-guided matching. ORB-SLAM uses `L - 4`,
    /// i.e. 2 for its `k = 10, L = 6` vocabulary.
    pub direct_index_level: u32,
    /// Covisibility-grouped candidate search (relocalisation, loops).
    pub candidates: CandidateParams,
}

impl Default for Params {
    fn default() -> Self {
        Self {
            direct_index_level: 2,
            candidates: CandidateParams::default(),
        }
    }
}

/// Errors of the BoW module.
#[derive(Debug, thiserror::Error)]
pub enum BowError {
    /// A file could not be read or written.
    #[error("i/o error on {path}: {source}")]
    Io {
        /// The file.
        path: PathBuf,
        /// The cause.
        source: std::io::Error,
    },
    /// The file does not start with the vocabulary magic bytes.
    #[error("not a shotpilot vocabulary file: magic bytes {found:02x?}, expected {expected:02x?}")]
    BadMagic {
        /// The first bytes of the file.
        found: [u8; 8],
        /// The magic this build expects.
        expected: [u8; 8],
    },
    /// The file's format version is not one this build reads.
    #[error(
        "vocabulary file version {found} is not supported (this build reads version {supported})"
    )]
    UnsupportedVersion {
        /// Version in the file.
        found: u32,
        /// Version this build reads.
        supported: u32,
    },
    /// The file is shorter than its header says.
    #[error("vocabulary file truncated: {needed} bytes needed, {found} present")]
    Truncated {
        /// Bytes the header implies.
        needed: u64,
        /// Bytes present.
        found: u64,
    },
    /// The file is longer than its header says.
    #[error("vocabulary file has {extra} unexpected trailing bytes")]
    TrailingBytes {
        /// Bytes after the checksum.
        extra: u64,
    },
    /// The checksum over the file's contents does not match the stored one.
    #[error(
        "vocabulary file corrupt: checksum {computed:#018x} differs from stored {stored:#018x}"
    )]
    ChecksumMismatch {
        /// Checksum stored in the file.
        stored: u64,
        /// Checksum of the bytes read.
        computed: u64,
    },
    /// The tree stored in a file (or imported) is not a valid vocabulary.
    #[error("invalid vocabulary structure at node {node}: {reason}")]
    InvalidStructure {
        /// The node where the problem shows.
        node: u32,
        /// What is wrong.
        reason: &'static str,
    },
    /// A line of a DBoW2 text vocabulary cannot be read.
    #[error("DBoW2 text vocabulary, line {line}: {reason}")]
    TextFormat {
        /// 1-based line number.
        line: usize,
        /// What is wrong.
        reason: String,
    },
    /// A vocabulary uses a scoring or weighting this module does not implement.
    #[error("unsupported {what} code {code} (supported: {supported})")]
    Unsupported {
        /// `"scoring"` or `"weighting"`.
        what: &'static str,
        /// The numeric code in the file.
        code: u32,
        /// The codes this module handles.
        supported: &'static str,
    },
    /// A parameter is outside its valid range.
    #[error("invalid parameter {name} = {value}: {reason}")]
    InvalidParam {
        /// Parameter name.
        name: &'static str,
        /// Its value.
        value: String,
        /// The valid range.
        reason: &'static str,
    },
    /// Training needs more data.
    #[error("not enough training data: {found} {what}, at least {needed} needed")]
    NotEnoughTrainingData {
        /// What is counted (`"images"`, `"descriptors"`).
        what: &'static str,
        /// How many were given.
        found: usize,
        /// How many are needed.
        needed: usize,
    },
    /// A keyframe id is already in the database.
    #[error("keyframe {id:?} is already in the database")]
    DuplicateKeyFrame {
        /// The keyframe.
        id: KeyFrameId,
    },
    /// A BoW vector refers to a word the vocabulary does not have.
    #[error("word {word} out of range: the vocabulary has {words} words")]
    WordOutOfRange {
        /// The word id.
        word: u32,
        /// Number of words.
        words: u32,
    },
}
