//! Measuring what a generator learned: Fréchet and kernel distances over pretrained features
//! ([`crate::pretrained`]), topology coverage and disentanglement from a probe trained on the
//! procedural dataset's ground truth, pose consistency, and the one-page report.
pub mod distance;
pub mod evaluator;
pub mod fidelity;
pub mod metrics;
pub mod probe;
pub mod provenance;
pub mod report;
pub mod result;
pub mod seeds;
