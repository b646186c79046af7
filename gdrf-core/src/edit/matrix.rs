//! The swap matrix, built one way everywhere (gdrf-edit's `matrix`, the trainer's previews,
//! the evaluation): cell (i, j) has the shape of item i and the appearance of item j, cells
//! in row-major order.
use super::{latents, Features};
use crate::camera::{Poses, Rays};
use crate::field::generator::Truncation;
use crate::render::{Noise, Renderer};
use crate::{Latents, Result};
use tch::Tensor;

/// The pairs of a k × k swap matrix over `items (k, …)` (codes, poses): the shape side's
/// item of each cell `(k², …)` (row i repeats item i) and the appearance side's (column j
/// is item j).
pub fn swap_pairs(items: &Tensor) -> (Tensor, Tensor) {
    let k = items.size()[0];
    let mut tile = vec![1; items.dim()];
    tile[0] = k;
    (items.repeat_interleave_self_int(k, 0, None), items.repeat(tile.as_slice()))
}

/// One view of a swap matrix: every (shape, appearance) pair of `features`.
pub struct MatrixView<'a> {
    pub renderer: &'a Renderer<'a>,
    pub features: &'a [Features],
    pub poses: &'a Poses,
    pub res: i64,
    pub noise: &'a Noise,
    pub trunc: Option<&'a Truncation>,
}

impl MatrixView<'_> {
    /// Cells `(1, 3, res, res)` in row-major order, each rendered in full.
    pub fn full(&self) -> Result<Vec<Tensor>> {
        let g = self.renderer.generator;
        let mut cells = Vec::new();
        for shape in self.features {
            for app in self.features {
                let lat = latents(g, shape, app, self.trunc);
                cells.push(self.renderer.render_image(&lat, self.poses, self.res, self.noise)?.rgb);
            }
        }
        Ok(cells)
    }

    /// The same cells with each row's shape side computed once and re-shaded per appearance.
    pub fn cached(&self) -> Result<Vec<Tensor>> {
        let (renderer, g, res) = (self.renderer, self.renderer.generator, self.res);
        let rays = Rays::from_poses(self.poses, res, renderer.camera.fov_deg);
        let mut cells = Vec::new();
        for shape in self.features {
            let shape_film = latents(g, shape, shape, self.trunc).shape;
            let sides =
                renderer.staged().shape_sides(&shape_film, &rays, self.noise, renderer.config.shade_min_weight)?;
            for app in self.features {
                let Latents { appearance, .. } = latents(g, shape, app, self.trunc);
                let pixel = renderer.staged().shade_chunks(&sides, &appearance)?;
                cells.push(pixel.permute([0, 2, 1]).reshape([1, 3, res, res]) * 2.0 - 1.0);
            }
        }
        Ok(cells)
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use tch::Kind;

    #[test]
    fn rows_share_the_shape_side_and_columns_the_appearance_side() {
        let items = Tensor::from_slice(&[10.0f32, 11.0, 20.0, 21.0, 30.0, 31.0]).reshape([3, 2]);
        let (shape, appearance) = swap_pairs(&items);
        assert_eq!(shape.size(), [9, 2]);
        for cell in 0..9i64 {
            let (i, j) = (cell / 3, cell % 3);
            assert!(shape.get(cell).equal(&items.get(i)), "cell {cell}");
            assert!(appearance.get(cell).equal(&items.get(j)), "cell {cell}");
        }
        let poses = Tensor::arange(4, (Kind::Float, tch::Device::Cpu));
        let (s, a) = swap_pairs(&poses);
        assert_eq!(Vec::<f32>::try_from(&s).unwrap(), [0., 0., 0., 0., 1., 1., 1., 1., 2., 2., 2., 2., 3., 3., 3., 3.]);
        assert_eq!(Vec::<f32>::try_from(&a).unwrap(), [0., 1., 2., 3., 0., 1., 2., 3., 0., 1., 2., 3., 0., 1., 2., 3.]);
    }
}
