//! libtorch's global generator: seeded sections under the library's lock, and the
//! initialisation's draws compared across two builds from one seed. In a test binary of
//! their own: the generator is shared by every thread of a process, and a unit test
//! drawing or seeding it in parallel (outside the lock, as tests may) would change the
//! numbers these compare.
use gdrf_core::config::HeadBias;
use gdrf_core::rng::{self, with_global_generator, with_global_seed};
use gdrf_core::{Generator, GeneratorConfig};
use tch::{nn, Device, Kind, Tensor};

/// The release's head bias is U(±1/√H), so its Δσ offset (×100) depends on the width;
/// `deform_head_bias = "zero"` starts every density at the template's, at any width,
/// and leaves every other initial weight as the release's draw makes it.
#[test]
fn the_zero_head_bias_adds_no_density_at_widths_64_and_256() {
    for h in [64usize, 256] {
        let cfg = |bias| GeneratorConfig {
            hidden_dim: h,
            latent_dim: 32,
            mapping_hidden_dim: 32,
            deform_head_frequency: 50.0,
            deform_head_bias: bias,
            ..Default::default()
        };
        let build = |bias| {
            rng::with_global_seed(0, || {
                let vs = nn::VarStore::new(Device::Cpu);
                let g = Generator::new(&vs.root(), &cfg(bias)).unwrap();
                (vs, g)
            })
        };
        let (uvs, uniform) = build(HeadBias::Uniform);
        let (zvs, zero) = build(HeadBias::Zero);
        // The release's draw: within ±1/√H, and not all zero.
        let b = uniform.deform.head.bias.detach();
        let bound = 1.0 / (h as f64).sqrt();
        assert!(f64::try_from(b.abs().max()).unwrap() <= bound, "H = {h}");
        assert!(f64::try_from(b.abs().max()).unwrap() > 0.0, "H = {h}");
        assert_eq!(f64::try_from(zero.deform.head.bias.abs().max()).unwrap(), 0.0, "H = {h}");
        // Δσ is exactly 0 everywhere for every code; Δx still differs between codes.
        // Every draw of this binary under the lock, so that the sections test beside it
        // sees only its own.
        let (z, x) = with_global_generator(|| {
            (Tensor::randn([2, 32], (Kind::Float, Device::Cpu)), Tensor::rand([2, 64, 3], (Kind::Float, Device::Cpu)))
        });
        let x = x * 2.0 - 1.0;
        let (dx, dsigma) = zero.deform.forward(&x, &zero.shape_from_z(&z, None));
        assert_eq!(f64::try_from(dsigma.abs().max()).unwrap(), 0.0, "H = {h}");
        assert!(f64::try_from((dx.get(0) - dx.get(1)).abs().max()).unwrap() > 0.0, "H = {h}");
        // Everything but the head's bias is the same draw.
        let (u, zv) = (uvs.variables(), zvs.variables());
        for (name, t) in &u {
            if name != "deform.head.bias" {
                assert!(t.equal(&zv[name]), "H = {h}: {name} differs");
            }
        }
    }
}

#[test]
fn seeded_sections_of_parallel_threads_do_not_interleave() {
    // Each section draws, yields, then draws again: without the lock another thread's
    // reseed between the two draws gives a second draw other than the seed's.
    let section = |seed: i64| -> Vec<f32> {
        with_global_seed(seed, || {
            let a = Tensor::randn([64], (Kind::Float, Device::Cpu));
            std::thread::yield_now();
            Vec::try_from(Tensor::cat(&[a, Tensor::randn([64], (Kind::Float, Device::Cpu))], 0)).unwrap()
        })
    };
    let want: Vec<Vec<f32>> = (0..4).map(section).collect();
    // Re-entrant on one thread: a network built inside a seeded section does not deadlock.
    assert_eq!(with_global_seed(0, || with_global_generator(|| section(0))), want[0]);
    std::thread::scope(|s| {
        let handles: Vec<_> = (0..4)
            .map(|seed| {
                let want = &want;
                s.spawn(move || (0..50).all(|_| section(seed) == want[seed as usize]))
            })
            .collect();
        for (seed, h) in handles.into_iter().enumerate() {
            assert!(h.join().unwrap(), "seed {seed}: a section drew other numbers");
        }
    });
}
