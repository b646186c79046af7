//! What a generator's checkpoint header says about how to score it: the resolution it
//! learned at, and whether the distances' features were its discriminator's.
/// The generator header's `info` key naming the discriminator it was trained against.
pub const DISCRIMINATOR_INFO: &str = "discriminator";

/// Said when a generator is scored at another resolution than the one it was trained at.
pub fn resolution_warning(header: &crate::checkpoint::Header, resolution: i64) -> Option<String> {
    let trained = header.trained_resolution()?;
    (trained != resolution).then(|| {
        let steps = header.trained_coarse_samples().map(|n| format!(" --samples {n}")).unwrap_or_default();
        format!(
            "this generator was trained at {trained}² and is rendered here at {resolution}²; \
             `--resolution {trained}{steps}` scores it where it learned, against the real images at {trained}²"
        )
    })
}

/// Said when a generator trained against the projected discriminator is scored with
/// EfficientNet-Lite0 features: the generator was optimised in that very feature space.
pub const SHARED_FEATURES_WARNING: &str = "this generator was trained against the projected discriminator, built on \
     EfficientNet-Lite0's frozen features, the very features the Fréchet and kernel distances use: the generator was \
     optimised in their space, so they are not independent judges of it (score it with --features inception, and \
     read the probe's scores and the images)";

/// Whether a generator (its header) was trained against the projected discriminator:
/// from the `info` its run wrote, or a training checkpoint's config.
pub fn trained_against_projected(h: &crate::checkpoint::Header) -> bool {
    let projected = crate::disc::DiscKind::Projected.name();
    h.info.get(DISCRIMINATOR_INFO).is_some_and(|k| k == projected)
        || h.training.as_ref().and_then(|t| t.pointer("/config/discriminator/kind")).and_then(|k| k.as_str())
            == Some(projected)
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn a_generator_trained_against_the_projected_discriminator_is_recognised() {
        use crate::checkpoint::Header;
        let plain = Header::generator(Default::default(), None);
        assert!(!trained_against_projected(&plain), "no provenance: no warning");
        let mut h = plain.clone();
        h.info.insert(DISCRIMINATOR_INFO.into(), "release".into());
        assert!(!trained_against_projected(&h));
        h.info.insert(DISCRIMINATOR_INFO.into(), "projected".into());
        assert!(trained_against_projected(&h));
        // A training checkpoint from before the info key: its config says so.
        let mut t = plain.clone();
        t.training = Some(serde_json::json!({"config": {"discriminator": {"kind": "projected"}}}));
        assert!(trained_against_projected(&t));
        t.training = Some(serde_json::json!({"config": {"discriminator": {"kind": "release"}}}));
        assert!(!trained_against_projected(&t));
    }

    #[test]
    fn scoring_at_another_resolution_than_training_is_said() {
        use crate::checkpoint::{Header, RESOLUTION_INFO, SAMPLES_PER_RAY_INFO};
        let mut h = Header::generator(Default::default(), None);
        assert_eq!(resolution_warning(&h, 64), None, "no provenance: no warning");
        assert_eq!((h.trained_resolution(), h.trained_coarse_samples()), (None, None));
        h.info.insert(RESOLUTION_INFO.into(), "32".into());
        h.info.insert(SAMPLES_PER_RAY_INFO.into(), "24".into());
        assert_eq!((h.trained_resolution(), h.trained_coarse_samples()), (Some(32), Some(12)));
        assert_eq!(resolution_warning(&h, 32), None);
        let w = resolution_warning(&h, 64).unwrap();
        assert!(w.contains("trained at 32²") && w.contains("`--resolution 32 --samples 12`"), "{w}");
        h.info.remove(SAMPLES_PER_RAY_INFO);
        assert!(resolution_warning(&h, 64).unwrap().contains("`--resolution 32`"));
    }
}
