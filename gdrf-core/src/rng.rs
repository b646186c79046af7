//! Counter-based random draws for training: every number of a step is a pure function of
//! (run seed, step, purpose, index), so a run resumed at step k draws exactly what the
//! uninterrupted run drew, on any device and thread count, and nothing reseeds or reads
//! libtorch's global generator.
//!
//! Element i of a draw is SplitMix64's output i for the draw's key: cheap (a few ns per
//! number), stateless, and independent across keys.
use tch::{Device, Kind, Tensor};

const GOLDEN: u64 = 0x9e37_79b9_7f4a_7c15;

/// SplitMix64's finaliser: a bijective 64-bit mix.
pub fn mix64(mut z: u64) -> u64 {
    z = (z ^ (z >> 30)).wrapping_mul(0xbf58_476d_1ce4_e5b9);
    z = (z ^ (z >> 27)).wrapping_mul(0x94d0_49bb_1331_11eb);
    z ^ (z >> 31)
}

/// Serialises every use of libtorch's global generator in this process.
static GLOBAL_GENERATOR: std::sync::Mutex<()> = std::sync::Mutex::new(());

thread_local! {
    /// Whether this thread holds `GLOBAL_GENERATOR` (so that nested sections go through).
    static HOLDS_GLOBAL: std::cell::Cell<bool> = const { std::cell::Cell::new(false) };
}

/// Runs `f` holding the process-wide lock on libtorch's global generator (re-entrant on
/// one thread). Every draw the library makes from that generator (network construction,
/// seeded codes) goes through here: the generator is shared by every thread of the
/// process, and a draw from another thread inside a seeded section changes its numbers.
pub fn with_global_generator<T>(f: impl FnOnce() -> T) -> T {
    if HOLDS_GLOBAL.with(|h| h.get()) {
        return f();
    }
    let _lock = GLOBAL_GENERATOR.lock().unwrap_or_else(|e| e.into_inner());
    struct Release;
    impl Drop for Release {
        fn drop(&mut self) {
            HOLDS_GLOBAL.with(|h| h.set(false));
        }
    }
    HOLDS_GLOBAL.with(|h| h.set(true));
    let _release = Release;
    f()
}

/// Runs `f` with libtorch's global generator seeded to `seed`, under
/// [`with_global_generator`]'s lock: no other thread's seeding or drawing (two trainers
/// being built, a seed's code drawn while a network initialises) lands in between.
pub fn with_global_seed<T>(seed: i64, f: impl FnOnce() -> T) -> T {
    with_global_generator(|| {
        tch::manual_seed(seed);
        f()
    })
}

/// What a draw is for; each purpose gives an independent stream within a step.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum Purpose {
    RealIndices = 1,
    RealFlips = 2,
    DiscCodes = 3,
    DiscPoses = 4,
    DiscJitter = 5,
    DiscImportance = 6,
    GenCodes = 7,
    GenPoses = 8,
    GenJitter = 9,
    GenImportance = 10,
    RegRays = 11,
    /// Codes of the fixed sample grids (drawn with step 0).
    SampleCodes = 12,
    /// The truncation centre's codes.
    Truncation = 13,
    /// Evaluation: codes, poses, subsets and the probe's batches.
    EvalCodes = 14,
    EvalPoses = 15,
    EvalSubsets = 16,
    ProbeBatches = 17,
    ProbeInit = 18,
    /// gdrf-edit's jitter and importance uniforms, shared by every image of a view.
    EditNoise = 19,
    /// gdrf-invert: renderer noise and ray subsets of each optimisation step.
    InvertNoise = 20,
    /// The coverage term's candidate codes and renderer noise.
    CoverageCodes = 21,
    CoverageJitter = 22,
    CoverageImportance = 23,
    /// The inversion initialiser's generated tuples and its batches.
    InitData = 24,
    InitBatches = 25,
    InitWeights = 26,
    /// The discriminator's input augmentation, in its step and in the generator's.
    DiscAugment = 27,
    GenAugment = 28,
    /// The colours real and generated images are composited on (`generator.background =
    /// "random"` or `"corners"`).
    RealBackground = 29,
    DiscBackground = 30,
    GenBackground = 31,
    /// The scaled-patch step's scales and offsets, shared by both players' updates.
    Patches = 32,
    /// The shape codes of the training-time occupancy grid's refreshes.
    OccupancyCodes = 33,
}

/// A source of uniform and normal tensors.
pub trait RandomSource {
    /// Uniform in [0, 1).
    fn uniform(&mut self, shape: &[i64]) -> Tensor;
    /// Standard normal.
    fn normal(&mut self, shape: &[i64]) -> Tensor;
}

/// libtorch's global generator (what `Tensor::rand` uses): for callers that do not need
/// reproducibility beyond `tch::manual_seed`.
#[derive(Debug, Clone, Copy)]
pub struct TorchRng {
    pub kind: Kind,
    pub device: Device,
}

impl RandomSource for TorchRng {
    fn uniform(&mut self, shape: &[i64]) -> Tensor {
        Tensor::rand(shape, (self.kind, self.device))
    }
    fn normal(&mut self, shape: &[i64]) -> Tensor {
        Tensor::randn(shape, (self.kind, self.device))
    }
}

/// The draws of one (seed, step, purpose). Successive calls continue the stream.
#[derive(Debug, Clone)]
pub struct StepRng {
    key: u64,
    draws: u64,
    pub kind: Kind,
    pub device: Device,
}

impl StepRng {
    pub fn new(seed: u64, step: u64, purpose: Purpose, kind: Kind, device: Device) -> Self {
        let key = mix64(mix64(seed ^ GOLDEN).wrapping_add(mix64(step.wrapping_mul(31).wrapping_add(purpose as u64))));
        Self { key, draws: 0, kind, device }
    }

    fn next_key(&mut self) -> u64 {
        self.draws += 1;
        mix64(self.key ^ mix64(self.draws))
    }

    /// `n` raw 64-bit values.
    pub fn u64s(&mut self, n: usize) -> Vec<u64> {
        let key = self.next_key();
        (0..n as u64).map(|i| mix64(key.wrapping_add((i + 1).wrapping_mul(GOLDEN)))).collect()
    }

    /// `n` integers uniform in [0, bound) (bound ≥ 1; the modulo bias is below 2⁻³²
    /// for any bound under 2³²).
    pub fn below(&mut self, n: usize, bound: u64) -> Vec<i64> {
        self.u64s(n).into_iter().map(|x| (x % bound.max(1)) as i64).collect()
    }

    fn numel(shape: &[i64]) -> usize {
        shape.iter().product::<i64>().max(0) as usize
    }

    fn tensor(&self, v: Vec<f32>, shape: &[i64]) -> Tensor {
        Tensor::from_slice(&v).view(shape).to_kind(self.kind).to_device(self.device)
    }
}

impl RandomSource for StepRng {
    /// 24-bit uniforms in [0, 1): exactly representable in float32, never 1.
    fn uniform(&mut self, shape: &[i64]) -> Tensor {
        let v = self.u64s(Self::numel(shape)).into_iter().map(|x| (x >> 40) as f32 / (1u64 << 24) as f32).collect();
        self.tensor(v, shape)
    }

    /// Box–Muller in float64 from two 53-bit uniforms per element (the cosine branch).
    fn normal(&mut self, shape: &[i64]) -> Tensor {
        let n = Self::numel(shape);
        let raw = self.u64s(2 * n);
        let unit = |x: u64| (x >> 11) as f64 / (1u64 << 53) as f64;
        let v = raw
            .chunks_exact(2)
            .map(|p| {
                let r = (-2.0 * (1.0 - unit(p[0])).ln()).sqrt();
                (r * (std::f64::consts::TAU * unit(p[1])).cos()) as f32
            })
            .collect();
        self.tensor(v, shape)
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    fn rng(step: u64, p: Purpose) -> StepRng {
        StepRng::new(7, step, p, Kind::Float, Device::Cpu)
    }

    #[test]
    fn same_key_same_numbers_other_keys_differ() {
        let a = rng(3, Purpose::GenCodes).normal(&[4, 5]);
        let b = rng(3, Purpose::GenCodes).normal(&[4, 5]);
        assert!(a.equal(&b));
        assert!(!a.equal(&rng(4, Purpose::GenCodes).normal(&[4, 5])));
        assert!(!a.equal(&rng(3, Purpose::DiscCodes).normal(&[4, 5])));
        assert!(!a.equal(&StepRng::new(8, 3, Purpose::GenCodes, Kind::Float, Device::Cpu).normal(&[4, 5])));
        // Successive draws of one stream differ.
        let mut r = rng(3, Purpose::GenCodes);
        assert!(!r.uniform(&[10]).equal(&r.uniform(&[10])));
    }

    #[test]
    fn moments_and_ranges() {
        let u = rng(1, Purpose::DiscJitter).uniform(&[200_000]);
        let (lo, hi) = (f64::try_from(u.min()).unwrap(), f64::try_from(u.max()).unwrap());
        assert!((0.0..1e-3).contains(&lo) && hi < 1.0 && hi > 0.999);
        assert!((u.mean(Kind::Double).double_value(&[]) - 0.5).abs() < 3e-3);
        let z = rng(1, Purpose::GenCodes).normal(&[200_000]);
        assert!(bool::try_from(z.isfinite().all()).unwrap());
        assert!(z.mean(Kind::Double).double_value(&[]).abs() < 1e-2);
        assert!((z.std(true).double_value(&[]) - 1.0).abs() < 1e-2);
        let idx = rng(1, Purpose::RealIndices).below(10_000, 7);
        assert!(idx.iter().all(|&i| (0..7).contains(&i)));
        assert!((0..7).all(|k| idx.contains(&k)));
    }
}
