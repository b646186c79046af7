//! A trainer as one rank of a data-parallel group ([`crate::dist`]): each rank takes its
//! equal share of every global batch, drawn exactly as one process draws the whole batch
//! (every draw comes from (seed, step, purpose) for the global batch, then is sliced: see
//! `Trainer::shard`), and after each network's backward the gradients and loss values are
//! averaged over the ranks before clipping (`Trainer::apply`). The ranks start from rank 0's
//! weights and stay identical replicas.
//!
//! A discriminator that looks across the images of a batch (a minibatch-std channel,
//! augmentation drawn for the batch) would see another batch on each rank, so then every
//! rank judges the global batch (`Trainer::judged_rows`): each renders only its own rows,
//! and the discriminator's work, small beside the renders, is repeated on every rank.
//! Otherwise each rank judges its own rows, and the top-k adversarial loss picks its k
//! among them, as the release's DistributedDataParallel does.
use super::Trainer;
use crate::dist::{ProcessGroup, Reduce};
use crate::{Error, Result};
use tch::{Kind, Tensor};

/// Bucket size of the gradient all-reduce: 4 MiB and more cost a third of 64 KiB buckets
/// on chairs-tiny's tensors (`gdrf-bench allreduce`, docs/benchmarks.md).
pub(crate) const GRADIENT_BUCKET_BYTES: usize = 16 << 20;

impl Trainer {
    /// Makes this trainer rank `group.rank()` of `group`: checks that every stage's batch
    /// splits into equal shares (each a multiple of the stage's `batch_split`, and even, so
    /// that the mode-seeking pairs stay on one rank), and that a batch judged globally is
    /// not split into chunks, and copies rank 0's networks to every rank. On CUDA the
    /// gradients go through NCCL.
    pub fn join_group(&mut self, group: ProcessGroup) -> Result<()> {
        let world = group.world() as i64;
        for (i, s) in self.cfg.stages.iter().enumerate() {
            let share = s.batch_size / world;
            if s.batch_size % world != 0 || share % s.batch_split != 0 || share % 2 != 0 {
                return Err(Error::Config(format!(
                    "stages[{i}].batch_size {} does not split into {world} ranks of an even share that \
                     batch_split {} divides",
                    s.batch_size, s.batch_split
                )));
            }
        }
        let d = &self.cfg.discriminator;
        let global = d.minibatch_std_group > 0 || !d.augment.is_empty();
        if let Some(i) = self.cfg.stages.iter().position(|s| global && s.batch_split > 1) {
            // Each chunk of a split batch would be judged with other images than in one process.
            return Err(Error::Config(format!(
                "stages[{i}].batch_split {} with {} on several ranks: the discriminator judges the \
                 global batch, which must then be judged in one piece (batch_split = 1)",
                self.cfg.stages[i].batch_split,
                if d.minibatch_std_group > 0 { "discriminator.minibatch_std_group" } else { "discriminator.augment" },
            )));
        }
        if self.device.is_cuda() {
            group.use_nccl_for_cuda()?;
        }
        for vs in [&self.gvs, &self.evs, &self.dvs] {
            let mut vars: Vec<_> = vs.variables().into_iter().collect();
            vars.sort_by(|a, b| a.0.cmp(&b.0));
            let tensors: Vec<_> = vars.into_iter().map(|(_, t)| t).collect();
            group.broadcast(&tensors, 0, GRADIENT_BUCKET_BYTES)?;
        }
        self.group = Some(group);
        Ok(())
    }

    /// Whether this process writes the run's files: alone, or as rank 0 of a group.
    pub fn is_writer(&self) -> bool {
        self.group.as_ref().is_none_or(|g| g.rank() == 0)
    }

    /// Seconds spent in the group's collectives so far (0 alone).
    pub fn comm_seconds(&self) -> f64 {
        self.group.as_ref().map_or(0.0, ProcessGroup::comm_seconds)
    }

    /// Waits until every rank of the group has reached it (returns at once alone).
    pub fn barrier(&self) -> Result<()> {
        self.group.as_ref().map_or(Ok(()), ProcessGroup::barrier)
    }

    /// This process's rank and the group's size ((0, 1) alone).
    pub fn rank_of(&self) -> (usize, usize) {
        self.group.as_ref().map_or((0, 1), |g| (g.rank(), g.world()))
    }

    /// Whether `flag` is raised on any rank (on this process alone, `flag`).
    pub(crate) fn any_rank(&self, flag: bool) -> Result<bool> {
        let Some(g) = &self.group else { return Ok(flag) };
        let t = [Tensor::from_slice(&[f64::from(u8::from(flag))])];
        g.all_reduce(&t, Reduce::Sum, 64)?;
        Ok(t[0].double_value(&[0]) > 0.0)
    }

    /// Whether every rank judges the global batch: several ranks, and a discriminator that
    /// looks across the images of a batch (see the module's documentation).
    pub(crate) fn judges_globally(&self) -> bool {
        let d = &self.cfg.discriminator;
        self.group.is_some() && (d.minibatch_std_group > 0 || !d.augment.is_empty())
    }

    /// What the discriminator sees of `own: (n, …)`, this rank's rows of a global batch:
    /// `own` itself, unless the ranks judge the global batch. Then it is that batch, the
    /// other ranks' rows as detached copies (gathered by summing zero-padded rows, which
    /// adds only zeros to each value) and this rank's rows as `own`, with its graph and its
    /// gradient scaled by the world size: each rank holds its own rows' part of the global
    /// batch's gradient, times the world size, and the average in `Trainer::apply` sums the
    /// parts.
    pub(crate) fn judged_rows(&self, own: &Tensor) -> Result<Tensor> {
        let Some(g) = self.group.as_ref().filter(|_| self.judges_globally()) else {
            return Ok(own.shallow_clone());
        };
        let (rank, world) = (g.rank() as i64, g.world() as i64);
        let n = own.size()[0];
        let mut shape = own.size();
        shape[0] = n * world;
        // Gloo sums float and double; a bfloat16 image travels as float, exactly.
        let wire = if own.kind() == Kind::Double { Kind::Double } else { Kind::Float };
        let all = Tensor::zeros(&shape, (wire, own.device()));
        all.narrow(0, rank * n, n).copy_(&own.detach());
        g.all_reduce(&[all.shallow_clone()], Reduce::Sum, GRADIENT_BUCKET_BYTES)?;
        let all = all.to_kind(own.kind());
        // The value of `own` exactly (x + 0·w), the gradient w times.
        let live = own.detach() + (own - own.detach()) * world as f64;
        Ok(Tensor::cat(&[all.narrow(0, 0, rank * n), live, all.narrow(0, (rank + 1) * n, (world - rank - 1) * n)], 0))
    }

    /// This rank's rows of `all`, a tensor of the global batch's rows (`rows_per_image`
    /// rows per image: e.g. a real image's candidate codes).
    pub(crate) fn own_rows(&self, all: &Tensor, rows_per_image: i64) -> Tensor {
        let (first, n) = self.shard(all.size()[0] / rows_per_image);
        all.narrow(0, first * rows_per_image, n * rows_per_image)
    }
}
