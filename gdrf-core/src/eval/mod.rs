//! Measuring what a generator learned: pretrained feature extractors (EfficientNet-Lite0,
//! FID's Inception-v3), Fréchet and kernel distances, perceptual distances, and a probe
//! trained on the procedural dataset's ground truth.
pub mod distance;
pub mod effnet;
pub mod fidelity;
pub mod inception;
pub mod lpips;
pub mod perceptual;
pub mod probe;
pub mod report;
pub mod seeds;
pub mod weights;
