//! The coverage term (see [`super::LossConfig::coverage_weight`]): implicit maximum
//! likelihood over the real images, so that every real image has a code that draws it.
use super::LossConfig;
use crate::camera::Poses;
use crate::render::{Noise, Renderer};
use crate::Result;
use tch::{Kind, Tensor};

/// A step's random draws for the coverage term: `coverage_candidates` codes per real image
/// `(B·k, latent)`, and the jitter and importance uniforms `(B, S², N)` of the nearest
/// candidates' renders.
pub struct CoverageDraws {
    pub candidates: Tensor,
    pub jitter: Tensor,
    pub importance: Tensor,
}

/// Picks, for each real image `(B, 3, S, S)` seen from `real_poses: (B, 2)`, the nearest of
/// its candidate codes at `coverage_resolution` (rendered by `renderers.0`, without
/// gradients), renders it at the real pose with gradients (`renderers.1`, in `split`
/// chunks, `samples` coarse samples per ray), and accumulates the MSE's gradient times
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
        let (img, _) = live.render_regions(&lat, &poses.narrow(c * chunk, chunk), res, 1, &noise)?;
        let m = (img - sl(real)).square().mean(Kind::Float);
        (&m * (weight / split as f64)).backward();
        mse += m.double_value(&[]) / split as f64;
    }
    Ok(Tensor::from(mse))
}
