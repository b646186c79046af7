//! Rendering inside occupancy grids: rays that meet no occupied cell cost one sample (the
//! far end), the others are sampled within their occupied interval
//! ([`crate::render::sampler::OccupiedBounds`]) or only in their occupied cells
//! ([`crate::render::sampler::OccupiedCells`]). A grid depends on the shape alone, so it
//! is built once per shape and reused for every view and every appearance.
use super::composite::composite;
use super::occupancy::{GridConfig, OccupancyGrid};
use super::rays::{Image, Noise, RayColours};
use super::renderer::Renderer;
use crate::camera::{Poses, Rays};
use crate::field::generator::Latents;
use crate::field::RadianceField;
use crate::nn::film::Film;
use crate::{Error, Result};
use tch::Tensor;

/// Rendering inside occupancy grids, a part of a renderer ([`Renderer::grids`]).
pub struct Grids<'r, 'a, F: RadianceField> {
    pub renderer: &'r Renderer<'a, F>,
}

impl<'r, 'a, F: RadianceField> Grids<'r, 'a, F> {
    pub fn new(renderer: &'r Renderer<'a, F>) -> Self {
        Self { renderer }
    }

    /// [`Renderer::render_image`], each image inside its shape's occupancy grid when `grids`
    /// holds one per image (empty: no grid). Also returns the density and colour queries
    /// spent.
    pub fn render_image_in_grids(
        &self,
        latents: &Latents,
        poses: &Poses,
        res: i64,
        noise: &Noise,
        grids: &[&OccupancyGrid],
    ) -> Result<(Image, (i64, i64))> {
        if !grids.is_empty() && grids.len() as i64 != poses.len() {
            return Err(Error::Shape(format!("{} occupancy grids for {} images", grids.len(), poses.len())));
        }
        // One image at a time: each has its own grid.
        self.renderer.render_image_with(latents, poses, res, noise, 1, |i, lat, rays, noise| match grids.get(i) {
            Some(grid) => self.render_in_grid(lat, rays, grid, noise),
            None => self.renderer.render_bundle(lat, rays, noise),
        })
    }

    /// The occupancy grid of one shape (row `i` of `shape`) for this renderer's camera.
    pub fn occupancy_grid(&self, shape: &Film, cfg: GridConfig) -> Result<OccupancyGrid> {
        OccupancyGrid::build(
            self.renderer.generator,
            shape,
            self.renderer.field,
            self.renderer.camera,
            cfg,
            self.renderer.config.chunk_points_on(shape.gamma.device()),
        )
    }

    /// Renders rays `(1, R, 3)` of one image inside its shape's `grid` (no gradients):
    /// rays that meet no occupied cell are shaded from their far-end sample alone (the
    /// reference's last interval is infinite, so that sample decides an empty ray's
    /// colour), the others are sampled within their occupied interval
    /// ([`Rays::bounds`]) by the density-first or the full path.
    fn render_in_grid(
        &self,
        latents: &Latents,
        rays: &Rays,
        grid: &OccupancyGrid,
        noise: &Noise,
    ) -> Result<RayColours> {
        if latents.batch_size() != 1 || rays.dirs.size()[0] != 1 {
            return Err(Error::Shape("render_in_grid renders one image at a time".into()));
        }
        tch::no_grad(|| {
            let r = rays.num_rays();
            let (support, hit) = self.support(rays, grid);
            let on = hit.nonzero().view([-1]);
            let off = hit.logical_not().nonzero().view([-1]);
            let (kind, device) = (rays.dirs.kind(), rays.dirs.device());
            let mut pixel = Tensor::zeros([1, r, 3], (kind, device));
            let mut depth = Tensor::zeros([1, r, 1], (kind, device));
            let mut opacity = Tensor::zeros([1, r, 1], (kind, device));
            let (mut density_evals, mut colour_evals) = (0, 0);
            let mut put = |idx: &Tensor, c: RayColours| {
                pixel = pixel.index_copy(1, idx, &c.pixel.to_kind(kind));
                depth = depth.index_copy(1, idx, &c.depth.to_kind(kind));
                opacity = opacity.index_copy(1, idx, &c.opacity.to_kind(kind));
                density_evals += c.density_evals;
                colour_evals += c.colour_evals;
            };
            if on.size()[0] > 0 {
                let sub = within(rays, &support, &on, grid.cfg.cells_only);
                put(&on, self.renderer.render_bundle(latents, &sub, &noise.select_rays(&on))?);
            }
            if off.size()[0] > 0 {
                put(&off, self.render_far_end(latents, &rays.select_rays(&off)));
            }
            Ok(RayColours { pixel, depth, opacity, density_evals, colour_evals })
        })
    }

    /// The pixels `(1, R, 3)` of one image's `rays` and the object's share of each `(1, R,
    /// 1)` ([`crate::render::RenderedRays::object_share`]: 0 for a ray shaded from its far
    /// end), rendered only in the occupied cells of
    /// `grid` (a [`GridConfig::cells_only`] grid), with gradients through the rays of
    /// `subset` (all when `None`): a ray that meets an occupied cell is sampled only in the
    /// occupied cells along it ([`crate::render::sampler::OccupiedCells`]), empty stretches
    /// counting as empty space; the others are shaded from their far-end sample alone. A
    /// ray's samples depend only on its own noise, so rendering the rays in groups (meets
    /// the grid or not, with gradients or not) gives the image one render would, and no
    /// ray twice.
    pub fn render_in_cells(
        &self,
        latents: &Latents,
        rays: &Rays,
        grid: &OccupancyGrid,
        noise: &Noise,
        subset: Option<&Tensor>,
    ) -> Result<(Tensor, Tensor)> {
        if !grid.cfg.cells_only {
            return Err(Error::Invalid("render_in_cells needs a grid that samples only its occupied cells".into()));
        }
        let r = rays.num_rays();
        let (occupied, hit) = self.support(rays, grid);
        let traced = match subset {
            None => hit.ones_like(),
            Some(idx) => hit.zeros_like().index_fill(0, idx, 1),
        };
        let (kind, device) = (rays.dirs.kind(), rays.dirs.device());
        let mut pixel = Tensor::zeros([1, r, 3], (kind, device));
        let mut share = Tensor::zeros([1, r, 1], (kind, device));
        for (meets, with_grad) in [(true, true), (true, false), (false, true), (false, false)] {
            let idx = hit.eq(meets as i64).logical_and(&traced.eq(with_grad as i64)).nonzero().view([-1]);
            if idx.size()[0] == 0 {
                continue;
            }
            let render = || -> Result<(Tensor, Tensor)> {
                Ok(if meets {
                    let sub = within(rays, &occupied, &idx, true);
                    let out = self.renderer.render_rays(latents, &sub, &noise.select_rays(&idx))?;
                    let s = out.object_share();
                    (out.pixel, s)
                } else {
                    // Its one sample stands for the background: no object.
                    let px = self.render_far_end(latents, &rays.select_rays(&idx)).pixel;
                    let s = px.narrow(2, 0, 1).zeros_like();
                    (px, s)
                })
            };
            let (px, s) = if with_grad { render()? } else { tch::no_grad(render)? };
            pixel = pixel.index_copy(1, &idx, &px.to_kind(kind));
            share = share.index_copy(1, &idx, &s.to_kind(kind));
        }
        Ok((pixel, share))
    }

    /// Where one image's rays `(1, R, 3)` may hold density by `grid`: their occupied bins
    /// `(1, R, M)` (a cells-only grid) or their occupied interval `(1, R, 2)`, and whether
    /// each meets an occupied cell `(R,)`.
    fn support(&self, rays: &Rays, grid: &OccupancyGrid) -> (Tensor, Tensor) {
        let (start, end) = (self.renderer.camera.ray_start, self.renderer.camera.ray_end);
        let (support, hit) =
            tch::no_grad(
                || {
                    if grid.cfg.cells_only {
                        grid.bins(rays, start, end)
                    } else {
                        grid.clip(rays, start, end)
                    }
                },
            );
        (support, hit.view([rays.num_rays()]))
    }

    /// Rays `(1, K, 3)` shaded from one sample at the camera's far end, integrated with
    /// the final interval as the reference integrates its last sample (gradients flow
    /// where autograd is enabled).
    fn render_far_end(&self, latents: &Latents, rays: &Rays) -> RayColours {
        let k = rays.num_rays();
        let x = &rays.origins + &rays.dirs * self.renderer.camera.ray_end;
        let (sigma, feature) = self.renderer.generator.sigma_feature(&x, &latents.shape, self.renderer.field);
        let rgb =
            self.renderer.generator.radiance(&feature, &self.renderer.sample_dirs(&rays.dirs, 1), &latents.appearance);
        let z = Tensor::full([1, k, 1, 1], self.renderer.camera.ray_end, (rays.dirs.kind(), rays.dirs.device()));
        let c = composite(&rgb.view([1, k, 1, 3]), &sigma.view([1, k, 1, 1]), &z, &self.renderer.composite_options());
        RayColours { pixel: c.pixel, depth: c.depth, opacity: c.opacity, density_evals: k, colour_evals: k }
    }
}

/// The rays `idx` of one image's `rays`, sampled only within their `support` (occupied bins
/// when `cells`, else their occupied interval) of [`Grids::support`].
fn within(rays: &Rays, support: &Tensor, idx: &Tensor, cells: bool) -> Rays {
    let (sub, support) = (rays.select_rays(idx), support.index_select(1, idx));
    if cells {
        sub.with_occupied(support)
    } else {
        sub.with_bounds(support)
    }
}
