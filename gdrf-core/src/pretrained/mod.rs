//! Pretrained networks and what is built on them, shared by the discriminator, inversion and
//! evaluation: EfficientNet-Lite0 (ImageNet), FID's Inception-v3 and LPIPS, their weight
//! files, and the perceptual distance on EfficientNet-Lite0's features.
pub mod effnet;
pub mod inception;
pub mod lpips;
pub mod perceptual;
pub mod weights;
