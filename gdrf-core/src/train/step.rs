//! One training step: the generator's draws, the discriminator's and the generator's
//! updates on the real batch (`reals.rs`; two renders, or one render shared by both
//! players), the draws and renderers of the coverage term (which the generator's objective
//! adds), and the guarded application of each update.
use super::occupancy::SharedGrid;
use super::optim::{clip_grads, grad_norm, zero_grads};
use super::parallel::GRADIENT_BUCKET_BYTES;
use super::scaled::{render_fakes, Placed, StepPatches};
use super::{discriminator_judgement, generator_judgement, patch_gradients, Judged};
use super::{Stage, StepKind, StepReport, Trainer};
use crate::camera::Poses;
use crate::disc::augment::AugmentedJudge;
use crate::disc::Judge;
use crate::dist::Reduce;
use crate::loss::coverage::CoverageDraws;
use crate::loss::deform_reg::reg_ray_count;
use crate::loss::{GeneratorObjective, Losses, Schedule};
use crate::render::{assemble, background_share, on_background, Noise, RenderedRays, Renderer};
use crate::rng::{Purpose, RandomSource, StepRng};
use crate::Result;
use std::time::Instant;
use tch::{Kind, Tensor};

impl Trainer {
    pub(super) fn rng(&self, step: i64, purpose: Purpose) -> StepRng {
        StepRng::new(self.cfg.seed, step as u64, purpose, Kind::Float, self.device)
    }

    /// Runs one step (D step, then G step) and returns what happened. A non-finite loss or
    /// gradient skips that network's update; `guard.rollback_after` such steps in a row
    /// roll back to the newest checkpoint with the learning rates scaled down.
    pub fn step(&mut self) -> Result<StepReport> {
        let start = Instant::now();
        let step = self.progress.step;
        let stage_index = self.cfg.stage_index(step);
        let stage = self.cfg.stages[stage_index].clone();
        let alpha = self.cfg.alpha(step);
        let (g_lr, d_lr) = self.cfg.learning_rates(step);
        let (g_lr, d_lr) = (g_lr * self.progress.lr_scale, d_lr * self.progress.lr_scale);
        let at = Schedule { step, alpha };
        let (b, res) = (stage.batch_size, stage.resolution);
        self.refresh_grid(step)?;

        let real_all = self.real_batch(&stage, step)?;
        let (real, real_poses) = self.real_seen(&real_all, &stage, step)?;
        let real_poses = real_poses.as_ref();
        let (d, g) = if g_lr <= 0.0 {
            // A discriminator-only stage: no generator render, no gradient, no EMA update.
            let d = self.discriminator_step(&stage, at, &real, real_poses, d_lr)?;
            (d, Update { total: f64::NAN, terms: Vec::new(), norm: f64::NAN, skipped: false })
        } else if self.cfg.step == StepKind::OneRender {
            let (d, losses) = self.one_render_gradients(&stage, at, &real, real_poses, d_lr)?;
            (d, self.generator_step(&stage, at, g_lr, &real_all.on_white, Some(losses))?)
        } else {
            let d = self.discriminator_step(&stage, at, &real, real_poses, d_lr)?;
            (d, self.generator_step(&stage, at, g_lr, &real_all.on_white, None)?)
        };

        let p = &mut self.progress;
        p.step += 1;
        p.images_seen += b;
        let bad = d.skipped || g.skipped;
        if bad {
            p.skipped_steps += 1;
            p.consecutive_bad += 1;
        } else {
            p.consecutive_bad = 0;
        }
        let seconds = start.elapsed().as_secs_f64();
        p.train_seconds += seconds;
        let mut report = StepReport {
            step,
            stage: stage_index,
            resolution: res,
            batch_size: b,
            alpha,
            d_total: d.total,
            g_total: g.total,
            d_terms: d.terms,
            g_terms: g.terms,
            grad_norm_d: d.norm,
            grad_norm_g: g.norm,
            lr_g: g_lr,
            lr_d: d_lr,
            d_skipped: d.skipped,
            g_skipped: g.skipped,
            seconds,
            rolled_back_to: None,
            occupancy: self.grid.as_ref().map(|g| g.occupied_fraction()),
        };
        if bad && self.progress.consecutive_bad >= self.cfg.guard.rollback_after {
            report.rolled_back_to = Some(self.rollback()?);
        }
        Ok(report)
    }

    /// Rendered images `img: (B, 3, R, R)` on white, of `parts` rendered by `renderer`,
    /// composited on `colours: (B, 3)` where given.
    fn on_colours(
        &self,
        img: &Tensor,
        parts: &[RenderedRays],
        renderer: &Renderer,
        colours: Option<&Tensor>,
    ) -> Tensor {
        let Some(colours) = colours else {
            return img.shallow_clone();
        };
        let o = renderer.composite_options();
        let shares: Vec<Tensor> = parts.iter().map(|p| background_share(&p.weights, &p.opacity, &o)).collect();
        on_background(img, &assemble(&shares, img.size()[2]), colours)
    }

    /// The live generator's renderer with sampling config `rc`, at the configured precision,
    /// clipping rays to the training-time occupancy grid where there is one.
    fn live_renderer<'a>(&'a self, rc: &'a crate::RenderConfig) -> Result<Renderer<'a>> {
        let mut r = Renderer::new(&self.generator, &self.cfg.camera, rc)?;
        r.field.compute_kind = self.cfg.precision.compute_kind(self.device);
        r.clip = self.grid.as_ref().map(|g| &g.grid);
        Ok(r)
    }

    /// Refreshes the training-time occupancy grid now, as the next step would when one is
    /// due (for benchmarks).
    pub fn refresh_grid_now(&mut self) -> Result<()> {
        let step = self.progress.step;
        let every = self.cfg.occupancy.as_ref().map_or(1, |o| o.every);
        self.refresh_grid(step.div_euclid(every) * every)
    }

    /// Builds the training-time occupancy grid at the run's first step under `[occupancy]`,
    /// and refreshes it every `occupancy.every` steps, from `occupancy.codes` shape codes of
    /// the step's own stream and the live generator as it stands before the step: every
    /// rank of a group builds the same grid, and a resumed run the uninterrupted run's.
    fn refresh_grid(&mut self, step: i64) -> Result<()> {
        let Some(oc) = self.cfg.occupancy.clone() else {
            self.grid = None;
            return Ok(());
        };
        if self.grid.is_some() && step % oc.every != 0 {
            return Ok(());
        }
        let z = self.rng(step, Purpose::OccupancyCodes).normal(&[oc.codes, self.cfg.generator.latent_dim as i64]);
        let rc = self.cfg.render_config(step);
        let grid = {
            // Builds query the lattice alone: the renderer's clip is never consulted.
            let renderer = self.live_renderer(&rc)?;
            let shapes = tch::no_grad(|| self.generator.shape_from_z(&z, None));
            SharedGrid::refresh(self.grid.as_ref(), &renderer, &shapes, &oc)?
        };
        self.grid = Some(grid);
        Ok(())
    }

    /// One player's fake batch of `stage` at `step` ([`Draws`]), from the draws
    /// `[codes, poses, jitter, importance, background]`, with the step's patches under the
    /// scaled-patch step.
    fn fake_draws(&self, stage: &Stage, step: i64, purposes: [Purpose; 5]) -> Draws {
        let (b, res, n) = (stage.batch_size, stage.judged_size(), stage.num_steps as i64);
        let [codes, poses, jitter, importance, background] = purposes;
        let z = self.rng(step, codes).normal(&[b, self.cfg.generator.latent_dim as i64]);
        let poses = Poses::sample_from(&self.cfg.camera, b, &mut self.rng(step, poses));
        let shape = [b, res * res, n];
        let noise = Noise {
            jitter: Some(self.rng(step, jitter).uniform(&shape)),
            importance: Some(self.rng(step, importance).uniform(&shape)),
        };
        // Drawn for the global batch, then this rank's rows.
        let (first, n) = self.shard(b);
        let rows = |t: &Tensor| t.narrow(0, first, n);
        let noise = Noise { jitter: noise.jitter.as_ref().map(rows), importance: noise.importance.as_ref().map(rows) };
        let (judged_z, judged_poses) = if self.judges_globally() {
            (z.shallow_clone(), poses.narrow(0, b))
        } else {
            (rows(&z), poses.narrow(first, n))
        };
        let background = self.random_background().then(|| rows(&self.background_colours(step, background, b)));
        let patches = self.step_patches(stage, step).map(|all| FakePatches {
            judged_at: self.judged_patches(&all).coords(self.device),
            own: all.rows(first, n),
        });
        Draws { z: rows(&z), poses: poses.narrow(first, n), noise, background, judged_z, judged_poses, patches }
    }

    /// `judge` seeing the images of `draws` where they lie: their patches under the
    /// scaled-patch step, whole images otherwise.
    fn placed<'a>(judge: &'a dyn Judge, draws: &Draws) -> Placed<'a> {
        Placed { inner: judge, at: draws.patches.as_ref().map(|p| p.judged_at.shallow_clone()) }
    }

    /// The discriminator behind the configured augmentation (`[discriminator] augment`),
    /// drawing from (seed, step, `purpose`); `None` when no augmentation is configured.
    fn augmented(&self, step: i64, purpose: Purpose) -> Option<AugmentedJudge<'_>> {
        let d = &self.cfg.discriminator;
        (!d.augment.is_empty())
            .then(|| AugmentedJudge::new(self.disc.as_ref(), &d.augment, d.augment_fill, self.rng(step, purpose)))
    }

    fn discriminator_step(
        &mut self,
        stage: &Stage,
        at: Schedule,
        real: &Tensor,
        real_poses: Option<&Tensor>,
        lr: f64,
    ) -> Result<Update> {
        let purposes = [
            Purpose::DiscCodes,
            Purpose::DiscPoses,
            Purpose::DiscJitter,
            Purpose::DiscImportance,
            Purpose::DiscBackground,
        ];
        let draws = self.fake_draws(stage, at.step, purposes);
        self.discriminator_step_on(stage, at, real, real_poses, &draws, lr)
    }

    /// The release's discriminator step on fakes of `draws`.
    fn discriminator_step_on(
        &mut self,
        stage: &Stage,
        at: Schedule,
        real: &Tensor,
        real_poses: Option<&Tensor>,
        draws: &Draws,
        lr: f64,
    ) -> Result<Update> {
        let rc = self.cfg.render_config(at.step);
        let renderer = self.live_renderer(&rc)?;
        // Fakes from the live generator, rendered without gradients (the release's D step).
        let Draws { z, poses, noise, background, patches, .. } = draws;
        let fakes = tch::no_grad(|| -> Result<Tensor> {
            let lat = self.generator.latents(z, z, None)?;
            let own = patches.as_ref().map(|p| &p.own);
            let (img, parts) = render_fakes(&renderer, &lat, (poses, noise), stage, own)?;
            Ok(self.on_colours(&img, &parts, &renderer, background.as_ref()))
        })?;
        let fakes = self.judged_rows(&fakes)?;
        let augmented = self.augmented(at.step, Purpose::DiscAugment);
        let judge = Self::placed(augmented.as_ref().map_or(self.disc.as_ref(), |a| a as &dyn Judge), draws);
        let losses = discriminator_judgement(
            &judge,
            real,
            real_poses,
            &fakes,
            &draws.judged_poses,
            Some(&draws.judged_z),
            at,
            &self.cfg.loss_at(at.step),
        )?;
        // Gradients are zeroed before each backward (R1's own gradient never accumulates).
        zero_grads(&self.dvs);
        losses.total.backward();
        self.apply(Net::D, &losses, lr)
    }

    /// The generator's update; `real` is the global batch's real images and poses (the
    /// coverage term's targets).
    fn generator_step(
        &mut self,
        stage: &Stage,
        at: Schedule,
        lr: f64,
        (real, real_poses): &(Tensor, Option<Tensor>),
        rendered_once: Option<Losses>,
    ) -> Result<Update> {
        // The one-render step has already left its gradient in G.
        let mut losses = match rendered_once {
            Some(l) => l,
            None => self.generator_gradients(stage, at)?,
        };
        let loss_cfg = self.cfg.loss_at(at.step);
        let objective = GeneratorObjective::new(&loss_cfg, at);
        if objective.coverage_weight() > 0.0 {
            losses = self.add_coverage(&objective, losses, (stage, at.step), real, real_poses.as_ref())?;
        }
        self.apply(Net::G, &losses, lr)
    }

    /// Adds the coverage term to `others`, the generator's other terms of `step`
    /// ([`GeneratorObjective::add_coverage`]), with this step's draws, on this rank's rows of
    /// the global batch `real` seen from `real_poses` (a per-image term: the ranks' average
    /// is the global batch's).
    fn add_coverage(
        &self,
        objective: &GeneratorObjective,
        others: Losses,
        (stage, step): (&Stage, i64),
        real: &Tensor,
        real_poses: Option<&Tensor>,
    ) -> Result<Losses> {
        let (b, res) = (real.size()[0], stage.judged_size());
        let k = self.cfg.loss.coverage_candidates;
        let latent = self.cfg.generator.latent_dim as i64;
        let shape = [b, res * res, stage.num_steps as i64];
        let (first, n) = self.shard(b);
        let draws = CoverageDraws {
            candidates: self.own_rows(&self.rng(step, Purpose::CoverageCodes).normal(&[b * k, latent]), k),
            jitter: self.own_rows(&self.rng(step, Purpose::CoverageJitter).uniform(&shape), 1),
            importance: self.own_rows(&self.rng(step, Purpose::CoverageImportance).uniform(&shape), 1),
            patches: self.step_patches(stage, step).map(|p| (p.rows(first, n).all, p.size)),
        };
        let real = self.own_rows(real, 1);
        let real_poses = real_poses.map(|p| self.own_rows(p, 1));
        let rc = self.cfg.render_config(step);
        // The candidates, without gradients or random draws (no jitter, mid-point importance
        // samples).
        let rc_candidates = crate::RenderConfig { jitter: false, ..rc.clone() };
        let renderers = (self.live_renderer(&rc_candidates)?, self.live_renderer(&rc)?);
        let samples = (stage.num_steps as i64, stage.batch_split);
        objective.add_coverage(others, &renderers, (&real, real_poses.as_ref()), &draws, samples)
    }

    /// Computes the generator's gradients of the step about to run and leaves them in
    /// the generator's variables, without updating anything (diagnostics and tests:
    /// e.g. the two-pass patch step must give the single-pass gradient). Returns the
    /// loss terms.
    pub fn generator_gradients_now(&mut self) -> Result<Vec<(&'static str, f64)>> {
        let step = self.progress.step;
        let stage = self.cfg.stage(step).clone();
        let at = Schedule { step, alpha: self.cfg.alpha(step) };
        Ok(self.generator_gradients(&stage, at)?.values())
    }

    /// Renders the generator's batch chunk by chunk and accumulates the gradient of the
    /// batch-mean loss into the generator's variables (D frozen throughout).
    fn generator_gradients(&mut self, stage: &Stage, at: Schedule) -> Result<Losses> {
        let draws = self.generator_draws(stage, at.step);
        // The generator step leaves D's parameters alone: frozen, they get no gradient.
        self.dvs.freeze();
        zero_grads(&self.gvs);
        let split = stage.batch_split;
        let mut mean = ChunkMean::default();
        // One augmentation stream for the step: successive chunks get successive draws.
        let augmented = self.augmented(at.step, Purpose::GenAugment);
        let judge = augmented.as_ref().map_or(self.disc.as_ref(), |a| a as &dyn Judge);
        let result = (|| -> Result<()> {
            for c in 0..split {
                let losses = self.generator_chunk(judge, stage, at, &draws.chunk(c, split), split as f64)?;
                mean.add(&losses, split);
            }
            Ok(())
        })();
        self.dvs.unfreeze();
        result?;
        Ok(mean.losses())
    }

    /// The generator's draws of `step`: codes, poses and renderer noise (in pairs sharing a
    /// pose and depths while the mode-seeking term is on, so that a pair's difference is
    /// its codes' alone), the regulariser rays, and whether a fault is injected.
    fn generator_draws(&mut self, stage: &Stage, step: i64) -> GenDraws {
        let (b, res) = (stage.batch_size, stage.judged_size());
        let purposes =
            [Purpose::GenCodes, Purpose::GenPoses, Purpose::GenJitter, Purpose::GenImportance, Purpose::GenBackground];
        let mut fakes = self.fake_draws(stage, step, purposes);
        if self.cfg.loss.diversity_at(step) > 0.0 {
            // Pairs (2i, 2i + 1) of the global batch; a rank's share starts at an even row.
            let pair = |t: &Option<Tensor>| t.as_ref().map(crate::camera::rows_in_pairs);
            fakes.noise = Noise { jitter: pair(&fakes.noise.jitter), importance: pair(&fakes.noise.importance) };
            fakes.background = pair(&fakes.background);
            fakes.poses = fakes.poses.in_pairs();
            fakes.judged_poses = fakes.judged_poses.in_pairs();
        }
        let n_reg = reg_ray_count(res * res, &self.cfg.loss.reg);
        let (first, n) = self.shard(b);
        let reg_rays =
            Tensor::from_slice(&self.rng(step, Purpose::RegRays).below((b * n_reg) as usize, (res * res) as u64))
                .view([b, n_reg])
                .narrow(0, first, n)
                .to_device(self.device);
        let debug = &self.cfg.debug;
        let on_this_rank =
            debug.inject_nonfinite_ranks.is_empty() || debug.inject_nonfinite_ranks.contains(&self.rank_of().0);
        let inject = debug.inject_nonfinite_steps.contains(&step) && on_this_rank && self.injected.insert(step);
        GenDraws { fakes, reg_rays, inject }
    }

    /// The one-render step ([`StepKind::OneRender`]) up to the generator's update: renders
    /// the generator's batch once with its graph, takes the discriminator's step on those
    /// images (detached), then leaves in G the gradient of the batch-mean loss through the
    /// updated discriminator on the same graph. Returns D's update and G's losses.
    fn one_render_gradients(
        &mut self,
        stage: &Stage,
        at: Schedule,
        real: &Tensor,
        real_poses: Option<&Tensor>,
        d_lr: f64,
    ) -> Result<(Update, Losses)> {
        let draws = self.generator_draws(stage, at.step);
        let split = stage.batch_split;
        let rc = self.cfg.render_config(at.step);
        zero_grads(&self.gvs);
        // Every chunk's graph is kept until the generator's backward.
        let rendered = {
            let renderer = self.live_renderer(&rc)?;
            (0..split)
                .map(|c| {
                    let d = draws.chunk(c, split);
                    let f = &d.fakes;
                    let lat = self.generator.latents(&f.z, &f.z, None)?;
                    let own = f.patches.as_ref().map(|p| &p.own);
                    let (img, parts) = render_fakes(&renderer, &lat, (&f.poses, &f.noise), stage, own)?;
                    let img = self.on_colours(&img, &parts, &renderer, f.background.as_ref());
                    Ok((d, lat, img, parts))
                })
                .collect::<Result<Vec<_>>>()?
        };
        let fakes = self.judged_rows(&Tensor::cat(&rendered.iter().map(|r| r.2.detach()).collect::<Vec<_>>(), 0))?;
        let d = {
            let augmented = self.augmented(at.step, Purpose::DiscAugment);
            let judge = augmented.as_ref().map_or(self.disc.as_ref(), |a| a as &dyn Judge);
            let judge = Self::placed(judge, &draws.fakes);
            let losses = discriminator_judgement(
                &judge,
                real,
                real_poses,
                &fakes,
                &draws.fakes.judged_poses,
                Some(&draws.fakes.judged_z),
                at,
                &self.cfg.loss_at(at.step),
            )?;
            zero_grads(&self.dvs);
            losses.total.backward();
            losses
        };
        let d = self.apply(Net::D, &d, d_lr)?;
        self.dvs.freeze();
        let mut mean = ChunkMean::default();
        let fault = if draws.inject { f64::NAN } else { 1.0 };
        let augmented = self.augmented(at.step, Purpose::GenAugment);
        let judge = augmented.as_ref().map_or(self.disc.as_ref(), |a| a as &dyn Judge);
        let result = (|| -> Result<()> {
            for (d, lat, img, parts) in &rendered {
                let img = self.judged_rows(img)?;
                let judged = Judged { img: &img, poses: &d.fakes.judged_poses, z: Some(&d.fakes.judged_z) };
                let mut losses = generator_judgement(
                    &self.generator,
                    &Self::placed(judge, &d.fakes),
                    &judged,
                    (lat, parts),
                    Some(&d.reg_rays),
                    at,
                    &self.cfg.loss_at(at.step),
                )?;
                losses.total = losses.total.g_mul_scalar(fault);
                (&losses.total / split as f64).backward();
                mean.add(&losses, split);
            }
            Ok(())
        })();
        self.dvs.unfreeze();
        result?;
        Ok((d, mean.losses()))
    }

    /// The one-render step's discriminator update (applied) and generator gradient (left in
    /// G's variables, not applied) for the step about to run; returns G's loss terms. With
    /// [`Trainer::discriminator_step_on_generator_draws_now`] and
    /// [`Trainer::generator_gradients_now`], the same step taken the release's way (tests).
    pub fn one_render_gradients_now(&mut self) -> Result<Vec<(&'static str, f64)>> {
        let step = self.progress.step;
        let stage = self.cfg.stage(step).clone();
        let at = Schedule { step, alpha: self.cfg.alpha(step) };
        let (_, d_lr) = self.cfg.learning_rates(step);
        let (real, real_poses) = self.real_batch(&stage, step).and_then(|r| self.real_seen(&r, &stage, step))?;
        let (_, losses) =
            self.one_render_gradients(&stage, at, &real, real_poses.as_ref(), d_lr * self.progress.lr_scale)?;
        Ok(losses.values())
    }

    /// The real images `(B, 3, S, S)` the discriminator judges in the step about to run: on
    /// white, or on that step's random colours unless the background is learned; resampled
    /// at the step's patches under the scaled-patch step (tests).
    pub fn judged_real_now(&mut self) -> Result<Tensor> {
        let step = self.progress.step;
        let stage = self.cfg.stage(step).clone();
        Ok(self.real_batch(&stage, step).and_then(|r| self.real_seen(&r, &stage, step))?.0)
    }

    /// The release's discriminator step (its own no-grad render) applied to the fakes of
    /// the generator's draws of the step about to run, instead of its own draws (tests).
    pub fn discriminator_step_on_generator_draws_now(&mut self) -> Result<()> {
        let step = self.progress.step;
        let stage = self.cfg.stage(step).clone();
        let at = Schedule { step, alpha: self.cfg.alpha(step) };
        let (_, d_lr) = self.cfg.learning_rates(step);
        let (real, real_poses) = self.real_batch(&stage, step).and_then(|r| self.real_seen(&r, &stage, step))?;
        let draws = self.generator_draws(&stage, step);
        let lr = d_lr * self.progress.lr_scale;
        self.discriminator_step_on(&stage, at, &real, real_poses.as_ref(), &draws.fakes, lr)?;
        Ok(())
    }

    /// Renders one chunk of the generator's batch, backpropagates its share of the loss
    /// (1/split of the chunk mean) into G's gradients and returns its (unscaled) losses.
    fn generator_chunk(
        &self,
        judge: &dyn Judge,
        stage: &Stage,
        at: Schedule,
        draws: &GenDraws,
        split: f64,
    ) -> Result<Losses> {
        let GenDraws { fakes, reg_rays, inject } = draws;
        let Draws { z, poses, noise, background, judged_z, judged_poses, patches } = fakes;
        let judge = &Self::placed(judge, fakes);
        let rc = self.cfg.render_config(at.step);
        let renderer = self.live_renderer(&rc)?;
        let gen = &self.generator;
        let cfg = &self.cfg.loss_at(at.step);
        let res = stage.resolution;
        let fault = if *inject { f64::NAN } else { 1.0 };
        if stage.regions == 1 {
            let lat = gen.latents(z, z, None)?;
            let (img, parts) = render_fakes(&renderer, &lat, (poses, noise), stage, patches.as_ref().map(|p| &p.own))?;
            let img = self.judged_rows(&self.on_colours(&img, &parts, &renderer, background.as_ref()))?;
            let judged = Judged { img: &img, poses: judged_poses, z: Some(judged_z) };
            let mut losses = generator_judgement(gen, judge, &judged, (&lat, &parts), Some(reg_rays), at, cfg)?;
            losses.total = losses.total.g_mul_scalar(fault);
            (&losses.total / split).backward();
            return Ok(losses);
        }
        let view = |img: &Tensor| self.judged_rows(img);
        patch_gradients(
            &renderer,
            judge,
            (z, poses, noise),
            (&view, judged_poses, judged_z),
            (res, stage.regions),
            reg_rays,
            at,
            cfg,
            (split, fault),
        )
    }

    /// Checks finiteness, clips and applies one network's update.
    fn apply(&mut self, net: Net, losses: &Losses, lr: f64) -> Result<Update> {
        let vs = match net {
            Net::G => &self.gvs,
            Net::D => &self.dvs,
        };
        let mut total = losses.total.double_value(&[]);
        let mut terms = losses.values();
        if let Some(group) = &self.group {
            // The global batch's gradient and losses: every rank's mean over its shard,
            // averaged. Before the norm, so clipping and the skip decision (a NaN on any
            // rank reaches all) see the same values on every rank.
            let grads: Vec<Tensor> =
                vs.trainable_variables().iter().map(|p| p.grad()).filter(|g| g.defined()).collect();
            group.all_reduce(&grads, Reduce::Average, GRADIENT_BUCKET_BYTES)?;
            let values: Vec<f64> = std::iter::once(total).chain(terms.iter().map(|(_, v)| *v)).collect();
            let values = [Tensor::from_slice(&values)];
            group.all_reduce(&values, Reduce::Average, GRADIENT_BUCKET_BYTES)?;
            let v = Vec::<f64>::try_from(&values[0])?;
            total = v[0];
            for (t, x) in terms.iter_mut().zip(&v[1..]) {
                t.1 = *x;
            }
        }
        let norm = grad_norm(vs);
        let ok = total.is_finite() && norm.is_finite();
        if ok {
            if self.cfg.optim.grad_clip > 0.0 {
                clip_grads(vs, norm, self.cfg.optim.grad_clip);
            }
            match net {
                Net::G => {
                    self.adam_g.step(&self.gvs, lr);
                    self.ema.update(&self.evs, &self.gvs);
                }
                Net::D => self.adam_d.step(&self.dvs, lr),
            }
        }
        Ok(Update { total, terms, norm, skipped: !ok })
    }

    /// This process's rows of a global batch of `b`: `(first, count)`; all of them in one
    /// process, rank r's equal share among several ([`Trainer::join_group`]).
    pub fn shard(&self, b: i64) -> (i64, i64) {
        match &self.group {
            Some(g) => {
                let n = b / g.world() as i64;
                (g.rank() as i64 * n, n)
            }
            None => (0, b),
        }
    }
}

/// One player's fake batch of a step ([`Trainer::fake_draws`]): this rank's codes
/// `(n, latent)`, poses, renderer noise and (with random backgrounds) background colours
/// `(n, 3)`, and the codes and poses of the batch the discriminator judges (the global
/// batch's where every rank judges it, else these: [`Trainer::judged_rows`]).
struct Draws {
    z: Tensor,
    poses: Poses,
    noise: Noise,
    background: Option<Tensor>,
    judged_z: Tensor,
    judged_poses: Poses,
    patches: Option<FakePatches>,
}

/// The scaled-patch step's patches of a player's fakes: this rank's, and `(n, 3)` the
/// coordinates of the judged batch's ([`Placed`]).
struct FakePatches {
    own: StepPatches,
    judged_at: Tensor,
}

/// The generator's random draws of one step ([`Trainer::generator_draws`]).
struct GenDraws {
    fakes: Draws,
    /// `(B, n)` rays of each image the regularisers are taken on.
    reg_rays: Tensor,
    /// A NaN is injected into this step's generator loss (`[debug]`).
    inject: bool,
}

impl GenDraws {
    /// Chunk `c` of `split` equal chunks of the batch (of the judged batch too: a batch
    /// judged globally is never split, see [`Trainer::join_group`]).
    fn chunk(&self, c: i64, split: i64) -> GenDraws {
        let f = &self.fakes;
        let len = f.z.size()[0] / split;
        let sl = |t: &Tensor| t.narrow(0, c * len, len);
        let judged_len = f.judged_z.size()[0] / split;
        GenDraws {
            fakes: Draws {
                z: sl(&f.z),
                poses: f.poses.narrow(c * len, len),
                noise: Noise {
                    jitter: f.noise.jitter.as_ref().map(sl),
                    importance: f.noise.importance.as_ref().map(sl),
                },
                background: f.background.as_ref().map(sl),
                judged_z: f.judged_z.narrow(0, c * judged_len, judged_len),
                judged_poses: f.judged_poses.narrow(c * judged_len, judged_len),
                patches: f.patches.as_ref().map(|p| FakePatches {
                    own: p.own.rows(c * len, len),
                    judged_at: p.judged_at.narrow(0, c * judged_len, judged_len),
                }),
            },
            reg_rays: sl(&self.reg_rays),
            inject: self.inject,
        }
    }
}

/// The batch mean of per-chunk losses (each chunk weighs 1/split).
#[derive(Default)]
struct ChunkMean {
    total: f64,
    terms: Vec<(&'static str, f64)>,
}

impl ChunkMean {
    fn add(&mut self, chunk: &Losses, split: i64) {
        self.total += chunk.total.double_value(&[]) / split as f64;
        for (i, (k, v)) in chunk.values().into_iter().enumerate() {
            if i == self.terms.len() {
                self.terms.push((k, 0.0));
            }
            self.terms[i].1 += v / split as f64;
        }
    }

    fn losses(&self) -> Losses {
        Losses {
            total: Tensor::from(self.total),
            terms: self.terms.iter().map(|(k, v)| (*k, Tensor::from(*v))).collect(),
        }
    }
}

#[derive(Clone, Copy)]
enum Net {
    G,
    D,
}

struct Update {
    total: f64,
    terms: Vec<(&'static str, f64)>,
    norm: f64,
    skipped: bool,
}
