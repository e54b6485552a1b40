//! Nothing: this package exists for its bench (`geometry.rs`, `ba_kornia.rs`).
