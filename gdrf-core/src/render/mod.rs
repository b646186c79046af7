//! Rendering: samplers place depths on rays, composite integrates along them, the
//! renderer ties field queries, sampling and integration together.
pub mod composite;
pub mod occupancy;
pub mod rays;
pub mod renderer;
pub mod samplers;
pub mod staged;

pub use composite::{composite, weights_from_density, Composite, CompositeOptions};
pub use occupancy::{GridConfig, OccupancyGrid};
pub use rays::{assemble_image, DensitySamples, Image, Noise, RayColours, RenderedRays};
pub use renderer::Renderer;
pub use staged::ShapeSide;
