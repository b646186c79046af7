//! The pure metrics of an evaluation, on images and the probe's predictions: foreground
//! colour histograms, the swap matrix's verdicts, pose errors (also in the generator's own
//! yaw frame), topology coverage, and real images seen through a lower resolution.
use super::probe::{class_histograms, total_variation, Predictions, FACTORS};
use tch::{Device, Kind, Tensor};

/// `imgs: (N, 3, S, S)` antialiased down to `low`² and bilinearly back up to S².
pub fn through_resolution(imgs: &Tensor, low: i64) -> Tensor {
    crate::io::resize(&crate::io::resize(imgs, low), imgs.size()[2])
}

/// A swap cell's verdicts (structure follows the row, colour follows the column); None
/// where the originals do not differ (and on the diagonal).
pub type Verdict = (Option<bool>, Option<bool>);

/// Bins per channel of the foreground colour histograms.
const HIST_BINS: i64 = 4;

/// `(N, 64)` normalised joint RGB histograms (4 bins per channel) of each image's
/// foreground — pixels at least 0.06 away from white in some channel — of `(N, 3, S, S)`
/// images in [−1, 1]. An image without foreground gets a zero histogram.
pub fn colour_histograms(images: &Tensor) -> Tensor {
    let x = ((images.to_kind(Kind::Float).to_device(Device::Cpu) + 1.0) / 2.0).clamp(0.0, 1.0);
    let (n, s) = (x.size()[0], x.size()[2] * x.size()[3]);
    let fg = x.min_dim(1, false).0.lt(0.94).view([n, s]).to_kind(Kind::Float);
    let bins = (x * HIST_BINS as f64).floor().clamp(0.0, (HIST_BINS - 1) as f64).to_kind(Kind::Int64).view([n, 3, s]);
    let idx = bins.select(1, 0) * (HIST_BINS * HIST_BINS) + bins.select(1, 1) * HIST_BINS + bins.select(1, 2);
    let hist = Tensor::zeros([n, HIST_BINS.pow(3)], (Kind::Float, Device::Cpu)).scatter_add(1, &idx, &fg);
    &hist / hist.sum_dim_intlist(1, true, Kind::Float).clamp_min(1.0)
}

/// The disentanglement rates of a k × k swap matrix (row-major: shape i, appearance j)
/// and each cell's verdict (structure follows i, colour follows j). Structure: the
/// probe's classes, over factors whose originals differ. Colour: the foreground colour
/// histograms ([`colour_histograms`], L1), over pairs whose originals differ by more than
/// 0.3 — the probe's own colour head is not used here because it reads part colours
/// partly from shape (on the dataset's own swaps its predictions followed the row).
pub(crate) fn swap_scores(pred: &Predictions, hist: &Tensor, k: i64) -> (f64, f64, Vec<Verdict>) {
    let classes = Vec::<i64>::try_from(pred.classes.flatten(0, -1)).unwrap();
    let cls = |i: i64, j: i64, f: usize| classes[((i * k + j) * 4) as usize + f];
    let h = |i: i64, j: i64| hist.get(i * k + j);
    let l1 = |a: &Tensor, b: &Tensor| f64::try_from((a - b).abs().sum(Kind::Double)).unwrap();
    let (mut s_hit, mut s_n, mut a_hit, mut a_n) = (0usize, 0usize, 0usize, 0usize);
    let mut verdicts = Vec::new();
    for i in 0..k {
        for j in 0..k {
            let (mut shape_ok, mut colour_ok) = (None, None);
            if i != j {
                for f in 0..4 {
                    if cls(i, i, f) != cls(j, j, f) {
                        s_n += 1;
                        let ok = cls(i, j, f) == cls(i, i, f);
                        s_hit += ok as usize;
                        shape_ok = Some(shape_ok.unwrap_or(true) && ok);
                    }
                }
                if l1(&h(i, i), &h(j, j)) > 0.3 {
                    a_n += 1;
                    let ok = l1(&h(i, j), &h(j, j)) < l1(&h(i, j), &h(i, i));
                    a_hit += ok as usize;
                    colour_ok = Some(ok);
                }
            }
            verdicts.push((shape_ok, colour_ok));
        }
    }
    let rate = |h: usize, n: usize| {
        if n == 0 {
            f64::NAN
        } else {
            h as f64 / n as f64
        }
    };
    (rate(s_hit, s_n), rate(a_hit, a_n), verdicts)
}

/// The probe's pose errors over a set of images, in degrees.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct PoseErrors {
    /// Mean |yaw error| (wrapped to ±180°).
    pub yaw: f64,
    /// Mean |yaw error| in the generator's own frame: after the one rotation about the up
    /// axis (`yaw_offset`) that makes it smallest. It tells images that do not turn with the
    /// camera (both errors high) from images that turn but whose yaw zero is not the data's
    /// (this one low). With yaw drawn from the full circle, only the discriminator's pose
    /// head on real images with known poses ties the two zeros together; without dataset
    /// poses nothing does, and this is the fair pose score.
    pub yaw_in_frame: f64,
    /// The rotation: probe yaw − rendered yaw, wrapped to [−180°, 180°).
    pub yaw_offset: f64,
    /// Mean |pitch error| (pitch is tied to the world's up axis: not aligned).
    pub pitch: f64,
    /// Mean signed pitch error, probe − rendered: the part of [`Self::pitch`] that a tilt
    /// common to every image explains (the rest is spread).
    pub pitch_bias: f64,
}

fn wrap_deg(x: f64) -> f64 {
    (x + 180.0).rem_euclid(360.0) - 180.0
}

/// The offset c minimising the mean of |wrap(dᵢ − c)| over yaw differences `d` (degrees),
/// and that mean. The mean is piecewise linear in c with convex kinks only at the dᵢ (at
/// dᵢ ± 180° the wrap makes concave ones), so its minimum is at one of them: trying each is
/// exact, and O(n²) is nothing at evaluation sizes.
fn best_yaw_offset(d: &[f64]) -> (f64, f64) {
    let mean_at = |c: f64| d.iter().map(|&x| wrap_deg(x - c).abs()).sum::<f64>() / d.len() as f64;
    let mut best = (0.0, mean_at(0.0));
    for &c in d {
        let m = mean_at(c);
        if m < best.1 {
            best = (wrap_deg(c), m);
        }
    }
    best
}

pub(crate) fn pose_errors(pred: &Predictions, truth: &Tensor) -> PoseErrors {
    let deg = 180.0 / std::f64::consts::PI;
    let t = truth.to_kind(Kind::Double).to_device(Device::Cpu);
    let p = pred.poses.to_kind(Kind::Double).to_device(Device::Cpu);
    let dy: Vec<f64> = Vec::try_from((p.select(1, 1) - t.select(1, 1)) * deg).unwrap();
    let dp = (p.select(1, 0) - t.select(1, 0)) * deg;
    let (yaw_offset, yaw_in_frame) = best_yaw_offset(&dy);
    PoseErrors {
        yaw: dy.iter().map(|&x| wrap_deg(x).abs()).sum::<f64>() / dy.len() as f64,
        yaw_in_frame,
        yaw_offset,
        pitch: f64::try_from(dp.abs().mean(Kind::Double)).unwrap(),
        pitch_bias: f64::try_from(dp.mean(Kind::Double)).unwrap(),
    }
}

pub(crate) fn coverage(pred: &Tensor, reference: &[Vec<f64>]) -> (f64, Vec<Vec<f64>>) {
    let h = class_histograms(pred);
    let tv = h.iter().zip(reference).map(|(a, b)| total_variation(a, b)).sum::<f64>() / FACTORS.len() as f64;
    (tv, h)
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::eval::result::Calibrated;

    #[test]
    fn through_resolution_keeps_smooth_images_and_removes_what_the_low_grid_cannot_hold() {
        let o = (Kind::Float, Device::Cpu);
        // A constant image comes back as it was.
        let flat = Tensor::full([1, 3, 16, 16], 0.3, o);
        let back = through_resolution(&flat, 4);
        assert_eq!(back.size(), [1, 3, 16, 16]);
        assert!(back.allclose(&flat, 1e-6, 1e-6, false));
        // A ±1 checkerboard has nothing a 4² grid can hold: away from the borders (where the
        // filter is renormalised) it averages to 0, to within 1e-3 of its amplitude (libtorch's
        // antialiasing weights cancel the alternation to 7e-4, not exactly).
        let idx = Tensor::arange(16, (Kind::Int64, Device::Cpu));
        let parity = (idx.view([16, 1]) + idx.view([1, 16])).remainder(2).to_kind(Kind::Float);
        let board = (parity * 2.0 - 1.0).view([1, 1, 16, 16]).expand([1, 3, 16, 16], false).contiguous();
        let inner = through_resolution(&board, 4).narrow(2, 4, 8).narrow(3, 4, 8);
        let worst = inner.abs().max().double_value(&[]);
        assert!(worst <= 1e-3, "largest |value| inside: {worst}");
    }

    #[test]
    fn swap_scores_count_only_informative_pairs() {
        // k = 2: originals differ in legs and colour (red vs blue); cell (0, 1) keeps 0's
        // legs and takes 1's colour, cell (1, 0) takes 0's legs and keeps 1's colour (both wrong).
        let classes = Tensor::from_slice(&[
            0i64, 1, 0, 0, /* (0,1) */ 0, 1, 0, 0, /* (1,0) */ 0, 1, 0, 0, /* (1,1) */ 3, 1, 0, 0,
        ])
        .view([4, 4]);
        let pred = Predictions {
            classes,
            colours: Tensor::zeros([4, 4, 3], (Kind::Float, Device::Cpu)),
            poses: Tensor::zeros([4, 2], (Kind::Float, Device::Cpu)),
        };
        let img = |r: f64, b: f64| {
            let t = Tensor::ones([1, 3, 4, 4], (Kind::Float, Device::Cpu));
            t.narrow(2, 1, 2)
                .narrow(3, 1, 2)
                .copy_(&Tensor::from_slice(&[r as f32, -1.0, b as f32]).view([1, 3, 1, 1]).expand([1, 3, 2, 2], false));
            t
        };
        let (red, blue) = (img(0.8, -1.0), img(-1.0, 0.8));
        let swap = Tensor::cat(&[red.shallow_clone(), blue.shallow_clone(), blue.shallow_clone(), blue], 0);
        let hist = colour_histograms(&swap);
        // Four foreground pixels of one colour: one bin holds all the mass; white is background.
        assert_eq!(f64::try_from(hist.get(0).sum(Kind::Double)).unwrap(), 1.0);
        assert_eq!(f64::try_from(hist.get(0).max()).unwrap(), 1.0);
        let (shape, app, verdicts) = swap_scores(&pred, &hist, 2);
        assert_eq!(shape, 0.5);
        assert_eq!(app, 0.5);
        let (t, f) = (Some(true), Some(false));
        assert_eq!(verdicts, vec![(None, None), (t, t), (f, f), (None, None)]);
        assert_eq!(
            f64::try_from(colour_histograms(&Tensor::ones([1, 3, 4, 4], (Kind::Float, Device::Cpu))).sum(Kind::Double))
                .unwrap(),
            0.0
        );
        let c = Calibrated::new(5.0, 1.0, 9.0);
        assert_eq!(c.position, 0.5);
    }

    fn poses(pitch_yaw_deg: &[(f64, f64)]) -> Tensor {
        let flat: Vec<f64> = pitch_yaw_deg.iter().flat_map(|&(p, y)| [p.to_radians(), y.to_radians()]).collect();
        Tensor::from_slice(&flat).view([-1, 2]).to_kind(Kind::Float)
    }

    #[test]
    fn yaw_error_is_measured_in_the_generators_own_frame() {
        // Rendered yaws around the circle; the probe reads each one turned by 90° (the
        // generator's frame) and off by +4°, −2°, 0°, +6°, +1°, so the best rotation is 91°
        // (their median) and leaves errors 3, 3, 1, 5, 0 (mean 2.4°); pitch is off by
        // 1, 3, 1, 3, 2 (mean 2°).
        let truth = poses(&[(60.0, -170.0), (60.0, -45.0), (70.0, 80.0), (50.0, 175.0), (60.0, 10.0)]);
        let pred = Predictions {
            classes: Tensor::zeros([5, 4], (Kind::Int64, Device::Cpu)),
            colours: Tensor::zeros([5, 4, 3], (Kind::Float, Device::Cpu)),
            poses: poses(&[(61.0, -76.0), (63.0, 43.0), (71.0, 170.0), (53.0, -89.0), (62.0, 101.0)]),
        };
        let e = pose_errors(&pred, &truth);
        let close = |a: f64, b: f64| (a - b).abs() < 1e-4;
        assert!(close(e.yaw_offset, 91.0), "{e:?}");
        assert!(close(e.yaw_in_frame, 2.4), "{e:?}");
        // Unaligned: 94, 88, 90, 96 (−89° − 175° = −264° wraps to 96°), 91.
        assert!(close(e.yaw, (94.0 + 88.0 + 90.0 + 96.0 + 91.0) / 5.0), "{e:?}");
        assert!(close(e.pitch, 2.0), "{e:?}");
        assert!(close(e.pitch_bias, 2.0), "every pitch read high: {e:?}");
        // A probe that reads the rendered yaw exactly: no rotation, no error.
        let exact = Predictions { poses: truth.shallow_clone(), ..pred };
        let e = pose_errors(&exact, &truth);
        assert_eq!((e.yaw, e.yaw_in_frame, e.yaw_offset, e.pitch, e.pitch_bias), (0.0, 0.0, 0.0, 0.0, 0.0));
    }

    #[test]
    fn the_best_yaw_offset_wraps_around_the_circle() {
        // Differences straddling ±180°: the best rotation is 180°, not their plain mean 0°.
        let (c, m) = best_yaw_offset(&[178.0, -178.0, 176.0, -176.0]);
        assert!((wrap_deg(c - 180.0)).abs() <= 4.0 && (m - 3.0).abs() < 1e-12, "{c} {m}");
        // Scanning every candidate is exact: a brute-force search over 0.01° steps never wins.
        let d = [10.0, 30.0, 35.0, -120.0, 170.0, -175.0, 90.0];
        let (_, m) = best_yaw_offset(&d);
        let brute = (0..36000)
            .map(|i| {
                let c = i as f64 / 100.0 - 180.0;
                d.iter().map(|&x| wrap_deg(x - c).abs()).sum::<f64>() / d.len() as f64
            })
            .fold(f64::INFINITY, f64::min);
        assert!(m <= brute + 1e-12 && brute - m < 1e-2, "{m} {brute}");
        assert_eq!(wrap_deg(180.0), -180.0);
        assert_eq!(wrap_deg(-190.0), 170.0);
    }
}
