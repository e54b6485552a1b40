//! Trajectory evaluation.
