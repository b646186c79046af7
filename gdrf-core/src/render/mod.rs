//! Rendering as a composition: a sampler (`sampler`: one [`Sampler`] per way of placing
//! samples) gives one [`RaySamples`] per bundle with its density, the field colours it,
//! `composite` integrates; the renderer ties them together for training, patches, chunked
//! inference; the staged shape-side path (`staged`) and rendering inside occupancy grids
//! (`in_grid`) are parts of a renderer that use it.
pub mod composite;
pub mod in_grid;
pub mod occupancy;
pub mod rays;
pub mod renderer;
pub mod sampler;
pub mod setup;
pub mod staged;

pub(crate) use composite::{background_share, on_background, wide};
pub use composite::{composite, weights_from_density, Composite, CompositeOptions};
pub use in_grid::Grids;
pub use occupancy::{camera_half_extent, GridChoice, GridConfig, OccupancyGrid, AUTO_GRID_SAMPLES, COARSEST};
pub use rays::{assemble, assemble_image, Image, Noise, RayColours, RaySamples, RenderedRays};
pub use renderer::Renderer;
pub use sampler::{Sampler, SamplerSpec, ShapeQuery};
pub use setup::Setup;
pub use staged::{ShapeSide, Staged};
