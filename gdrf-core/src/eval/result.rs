//! What an evaluation finds: every score at the model and at its two calibrated ends, the
//! class histograms, the pose frames, and the images the report shows.
use super::metrics::Verdict;
use serde::Serialize;
use tch::Tensor;

/// One score at the model and at both ends.
#[derive(Debug, Clone, Serialize)]
pub struct Calibrated {
    pub model: f64,
    /// Real held-out images: what a perfect generator gets.
    pub real: f64,
    /// A random-weight generator of the same architecture.
    pub random: f64,
    /// Where the model stands: 0 at the random end, 1 at the real end.
    pub position: f64,
}

impl Calibrated {
    pub(crate) fn new(model: f64, real: f64, random: f64) -> Self {
        let span = real - random;
        let position = if span.abs() > 1e-12 { (model - random) / span } else { f64::NAN };
        Self { model, real, random, position }
    }
}

/// The real images' scores when seen at a lower resolution ([`EvalOptions::real_resolution`]).
#[derive(Debug, Clone, Serialize)]
pub struct LowResolutionEnd {
    pub resolution: i64,
    pub frechet: f64,
    pub kernel: f64,
    pub coverage_tv: f64,
    pub shape_follows: f64,
    pub appearance_follows: f64,
    pub pose_yaw_error_deg: f64,
    pub pose_yaw_error_in_frame_deg: f64,
    pub pose_pitch_error_deg: f64,
    /// The mean signed pitch error ([`EvalResult::pitch_bias_deg`]).
    pub pitch_bias_deg: f64,
}

/// A pose offset found for the model, the real images and the random generator (degrees):
/// the yaw rotation of each one's frame, or its mean signed pitch error.
#[derive(Debug, Clone, Serialize)]
pub struct FrameOffsets {
    pub model: f64,
    pub real: f64,
    pub random: f64,
}

#[derive(Debug, Serialize)]
pub struct ClassTable {
    pub factor: String,
    pub classes: Vec<String>,
    /// Held-out split, true classes.
    pub reference: Vec<f64>,
    pub real_predicted: Vec<f64>,
    pub model: Vec<f64>,
    pub random: Vec<f64>,
}

#[derive(Debug, Serialize)]
pub struct EvalResult {
    pub generator: String,
    pub dataset: String,
    pub features: String,
    /// The evaluation seed: codes, poses, the random generator, kernel-distance subsets.
    pub seed: u64,
    pub images: i64,
    pub resolution: i64,
    pub samples_per_ray: i64,
    /// The model's truncation ψ ([`EvalOptions::psi`]; 1 = none).
    pub psi: f64,
    pub frechet: Calibrated,
    pub kernel: Calibrated,
    /// Set when a Fréchet distance had to be regularised (few samples).
    pub warnings: Vec<String>,
    pub coverage_tv: Calibrated,
    pub classes: Vec<ClassTable>,
    pub shape_follows: Calibrated,
    pub appearance_follows: Calibrated,
    pub pose_yaw_error_deg: Calibrated,
    /// After turning each distribution's yaw by one rotation (see [`PoseErrors::yaw_in_frame`]).
    pub pose_yaw_error_in_frame_deg: Calibrated,
    /// That rotation, per distribution.
    pub yaw_frame_offset_deg: FrameOffsets,
    pub pose_pitch_error_deg: Calibrated,
    /// The pitch error's mean sign, probe − rendered, per distribution: how much of it is a
    /// tilt every image shares ([`PoseErrors::pitch_bias`]).
    pub pitch_bias_deg: FrameOffsets,
    /// The real images seen at a lower resolution, when asked for.
    #[serde(skip_serializing_if = "Option::is_none")]
    pub real_at_resolution: Option<LowResolutionEnd>,
    pub probe_held_out_accuracy: Vec<f64>,
    pub seconds: f64,
    #[serde(skip)]
    pub samples: Tensor,
    #[serde(skip)]
    pub swap_images: Tensor,
    #[serde(skip)]
    pub swap_verdicts: Vec<Verdict>,
    #[serde(skip)]
    pub swap_side: i64,
}
