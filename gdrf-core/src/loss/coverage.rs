//! The coverage term (see [`super::LossConfig::coverage_weight`]): implicit maximum
//! likelihood over the real images, so that every real image has a code that draws it.
use super::LossConfig;
use crate::camera::patch::{patch_rays, real_patches, Patch};
use crate::camera::Poses;
use crate::render::{assemble_image, Noise, Renderer};
use crate::Result;
use tch::{Kind, Tensor};

/// A step's random draws for the coverage term: `coverage_candidates` codes per real image
/// `(B·k, latent)`, the jitter and importance uniforms `(B, S², N)` of the nearest
/// candidates' renders, and under the scaled-patch step the step's patches of these images
/// and their side P (then S = P: only the patch is rendered with gradients, and compared
/// with the real image resampled at it, so that the term costs what the patch costs).
pub struct CoverageDraws {
    pub candidates: Tensor,
    pub jitter: Tensor,
    pub importance: Tensor,
    pub patches: Option<(Vec<Patch>, i64)>,
}

/// Picks, for each real image `(B, 3, R, R)` seen from `real_poses: (B, 2)`, the nearest of
/// its candidate codes at `coverage_resolution` (rendered by `renderers.0`, without
/// gradients), renders it at the real pose with gradients (`renderers.1`, in `split`
/// chunks, `samples` coarse samples per ray; the whole image, or its patch in `draws`), and
/// accumulates the MSE's gradient times
/// `weight` (the step's, [`LossConfig::coverage_at`]) into the generator. Returns the MSE.
pub fn coverage_gradients(
    (candidates, live): &(Renderer, Renderer),
    real: &Tensor,
    real_poses: &Tensor,
    draws: &CoverageDraws,
    (samples, split): (i64, i64),
    cfg: &LossConfig,
    weight: f64,
) -> Result<Tensor> {
    let (b, res) = (real.size()[0], real.size()[2]);
    let k = cfg.coverage_candidates;
    let small = cfg.coverage_resolution.min(res);
    let z = &draws.candidates;
    let gen = live.generator;
    let poses = Poses::from_stacked(&real_poses.repeat_interleave_self_int(k, 0, None));
    let rendered = tch::no_grad(|| {
        let lat = gen.latents(z, z, None)?;
        let noise = Noise::midpoints(b * k, small * small, samples, z.device());
        candidates.render_image(&lat, &poses, small, &noise)
    })?
    .rgb;
    let target = crate::io::resize(real, small).repeat_interleave_self_int(k, 0, None);
    let dist = (rendered - target).square().mean_dim([1i64, 2, 3].as_slice(), false, Kind::Float).view([b, k]);
    let best = dist.argmin(1, false) + Tensor::arange(b, (Kind::Int64, dist.device())) * k;
    let z_best = z.index_select(0, &best);
    let poses = Poses::from_stacked(real_poses);
    let chunk = b / split;
    let mut mse = 0.0;
    for c in 0..split {
        let sl = |t: &Tensor| t.narrow(0, c * chunk, chunk);
        let noise = Noise { jitter: Some(sl(&draws.jitter)), importance: Some(sl(&draws.importance)) };
        let zc = sl(&z_best);
        let lat = gen.latents(&zc, &zc, None)?;
        let poses = poses.narrow(c * chunk, chunk);
        let (img, target) = match &draws.patches {
            None => (live.render_regions(&lat, &poses, res, 1, &noise)?.0, sl(real)),
            Some((patches, p)) => {
                let own = &patches[(c * chunk) as usize..((c + 1) * chunk) as usize];
                let part =
                    live.render_rays_chunked(&lat, &patch_rays(&poses, own, *p, res, live.camera.fov_deg)?, &noise)?;
                (assemble_image(std::slice::from_ref(&part), *p), real_patches(&sl(real), own, *p)?)
            }
        };
        let m = (img - target).square().mean(Kind::Float);
        (&m * (weight / split as f64)).backward();
        mse += m.double_value(&[]) / split as f64;
    }
    Ok(Tensor::from(mse))
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::{CameraConfig, Generator, GeneratorConfig, RenderConfig};
    use tch::{nn, Device};

    /// The term's MSE and the gradient it leaves in the generator's variables (by name).
    fn gradient(
        g: &Generator,
        vs: &nn::VarStore,
        real: &Tensor,
        poses: &Tensor,
        draws: &CoverageDraws,
    ) -> (f64, Vec<Tensor>) {
        let (cam, rc) = (CameraConfig::chair(), RenderConfig { num_steps: 4, chunk_points: 60, ..Default::default() });
        // The candidates without jitter, as the trainer renders them: nothing random.
        let still = RenderConfig { jitter: false, ..rc.clone() };
        let renderers = (Renderer::new(g, &cam, &still).unwrap(), Renderer::new(g, &cam, &rc).unwrap());
        let cfg = LossConfig { coverage_candidates: 3, coverage_resolution: 4, ..Default::default() };
        for (_, v) in vs.variables() {
            let mut grad = v.grad();
            if grad.defined() {
                let _ = grad.zero_();
            }
        }
        let mse = coverage_gradients(&renderers, real, poses, draws, (4, 2), &cfg, 1.0).unwrap().double_value(&[]);
        let mut v = vs.variables().into_iter().collect::<Vec<_>>();
        v.sort_by(|a, b| a.0.cmp(&b.0));
        (mse, v.iter().filter(|(_, t)| t.grad().defined()).map(|(_, t)| t.grad().copy()).collect())
    }

    /// Under the scaled-patch step the nearest candidate is rendered at its patch alone and
    /// compared with the real image resampled there: whole-image patches at P = R give the
    /// whole-image term, its MSE and gradient; native patches (s = P/R, whole-pixel
    /// offsets) the term over those pixels of the whole render.
    #[test]
    fn the_term_on_patches_is_the_term_on_their_pixels() {
        tch::manual_seed(11);
        let mut vs = nn::VarStore::new(Device::Cpu);
        let g = Generator::new(&vs.root(), &GeneratorConfig::tiny()).unwrap();
        vs.double();
        let opts = (Kind::Double, Device::Cpu);
        let (b, r, p, n) = (2, 6, 3, 4);
        let real = Tensor::rand([b, 3, r, r], opts) * 2.0 - 1.0;
        let poses = Poses::from_angles(&[(1.0, 0.2), (1.3, -2.0)], Kind::Double, Device::Cpu).stacked();
        let candidates = Tensor::randn([b * 3, 8], opts);
        let jitter = Tensor::rand([b, r * r, n], opts);
        let importance = Tensor::rand([b, r * r, n], opts);
        let whole = CoverageDraws {
            candidates: candidates.shallow_clone(),
            jitter: jitter.shallow_clone(),
            importance: importance.shallow_clone(),
            patches: None,
        };
        let (mse, grad) = gradient(&g, &vs, &real, &poses, &whole);
        assert!(mse > 0.0 && !grad.is_empty());
        let as_patches = CoverageDraws { patches: Some((vec![Patch::whole(); 2], r)), ..whole };
        let (mse_p, grad_p) = gradient(&g, &vs, &real, &poses, &as_patches);
        assert!((mse - mse_p).abs() <= 1e-12 * mse, "{mse} vs {mse_p}");
        assert_eq!(grad.len(), grad_p.len());
        for (a, b) in grad.iter().zip(&grad_p) {
            assert!(a.allclose(b, 1e-10, 1e-12, false), "max diff {}", (a - b).abs().max());
        }
        // Native 3² patches at pixels (x 2, y 1) and (x 3, y 3) of the 6² images, with the
        // whole image's noise at those pixels: the MSE over those pixels of the whole
        // render, which the candidate search (at 4², the same for both) left alone.
        let at = [(2i64, 1i64), (3, 3)];
        let patches: Vec<Patch> = at
            .iter()
            .map(|&(x, y)| Patch { scale: p as f64 / r as f64, offset: (x as f64 / r as f64, y as f64 / r as f64) })
            .collect();
        let pixels = |t: &Tensor| {
            let rows: Vec<Tensor> = at
                .iter()
                .enumerate()
                .map(|(i, &(x, y))| {
                    let idx: Vec<i64> = (0..p).flat_map(|v| (0..p).map(move |u| (y + v) * r + x + u)).collect();
                    t.get(i as i64).index_select(0, &Tensor::from_slice(&idx))
                })
                .collect();
            Tensor::stack(&rows, 0)
        };
        let native = CoverageDraws {
            candidates: candidates.shallow_clone(),
            jitter: pixels(&jitter),
            importance: pixels(&importance),
            patches: Some((patches, p)),
        };
        let (mse_n, _) = gradient(&g, &vs, &real, &poses, &native);
        // The whole-image render of the same nearest codes, on those pixels.
        let (cam, rc) = (CameraConfig::chair(), RenderConfig { num_steps: 4, chunk_points: 60, ..Default::default() });
        let live = Renderer::new(&g, &cam, &rc).unwrap();
        let still = RenderConfig { jitter: false, ..rc.clone() };
        let cand = Renderer::new(&g, &cam, &still).unwrap();
        let z = tch::no_grad(|| {
            let lat = g.latents(&candidates, &candidates, None).unwrap();
            let ps = Poses::from_stacked(&poses.repeat_interleave_self_int(3, 0, None));
            let img = cand.render_image(&lat, &ps, 4, &Noise::midpoints(b * 3, 16, 4, Device::Cpu)).unwrap().rgb;
            let target = crate::io::resize(&real, 4).repeat_interleave_self_int(3, 0, None);
            let d = (img - target).square().mean_dim([1i64, 2, 3].as_slice(), false, Kind::Float).view([b, 3]);
            candidates.index_select(0, &(d.argmin(1, false) + Tensor::arange(b, (Kind::Int64, Device::Cpu)) * 3))
        });
        let want = tch::no_grad(|| {
            let lat = g.latents(&z, &z, None).unwrap();
            let noise = Noise { jitter: Some(jitter.shallow_clone()), importance: Some(importance.shallow_clone()) };
            let (img, _) = live.render_regions(&lat, &Poses::from_stacked(&poses), r, 1, &noise).unwrap();
            let err =
                (img - &real).square().sum_dim_intlist([1i64].as_slice(), false, Kind::Double).view([b, r * r, 1]);
            f64::try_from(pixels(&err).sum(Kind::Double)).unwrap() / (b * 3 * p * p) as f64
        });
        // The term takes its mean in float32.
        assert!((mse_n - want).abs() <= 1e-6 * want, "{mse_n} vs {want}");
    }
}
