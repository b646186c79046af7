//! Rendering as a composition: the sampler (`sampler`, with the depth placements of
//! `samplers`) gives one [`RaySamples`] per bundle with its density, the field colours it,
//! `composite` integrates; the renderer ties them together for training, patches, chunked
//! inference, the staged shape-side path and occupancy grids.
pub mod composite;
pub mod occupancy;
pub mod rays;
pub mod renderer;
pub mod sampler;
pub mod samplers;
pub mod staged;

pub(crate) use composite::{background_share, on_background};
pub use composite::{composite, weights_from_density, Composite, CompositeOptions};
pub use occupancy::{GridChoice, GridConfig, OccupancyGrid, AUTO_GRID_SAMPLES};
pub use rays::{assemble, assemble_image, Image, Noise, RayColours, RaySamples, RenderedRays};
pub use renderer::Renderer;
pub use staged::ShapeSide;
