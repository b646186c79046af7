//! Generative Deformable Radiance Fields (GDRF) on libtorch.
//!
//! Data flows one way: a [`camera`] makes rays, a [`render::samplers`] places depths on
//! them, the [`field`] answers density first (shape side: deformation Φ and template
//! trunk T_σ) and colour second (appearance side: T_c from the density feature), and
//! [`render::composite`] integrates along each ray. [`render::renderer`] ties these
//! together for training batches, patches and chunked inference.
//!
//! Conventions follow the authors' release (see the reference specification): poses are
//! (pitch φ from +y, yaw θ), cameras sit on the unit sphere and look at the origin with
//! OpenGL axes, images are `(B, 3, H, W)` in `[-1, 1]`.
pub mod bench;
pub mod camera;
pub mod checkpoint;
pub mod config;
pub mod data;
pub mod device;
pub mod disc;
pub mod dist;
pub mod edit;
pub mod error;
pub mod eval;
pub mod field;
pub mod invert;
pub mod io;
pub mod loss;
pub mod mesh;
pub mod nn;
pub mod paths;
pub mod plot;
pub mod pretrained;
pub mod progress;
pub mod render;
pub mod rng;
pub mod stats;
pub mod train;

pub use config::{Background, CameraConfig, GeneratorConfig, PoseDistribution, RenderConfig};
pub use error::{Error, Result};
pub use field::generator::{Generator, Latents};
pub use nn::film::Film;
