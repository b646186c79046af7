//! A trainer as one rank of a data-parallel group ([`crate::dist`]): each rank takes its
//! equal share of every global batch, drawn exactly as one process draws the whole batch
//! (every draw comes from (seed, step, purpose) for the global batch, then is sliced: see
//! `Trainer::shard`), and after each network's backward the gradients and loss values are
//! averaged over the ranks before clipping (`Trainer::apply`). The ranks start from rank 0's
//! weights and stay identical replicas.
use super::Trainer;
use crate::dist::{ProcessGroup, Reduce};
use crate::{Error, Result};
use tch::Tensor;

/// Bucket size of the gradient all-reduce: 4 MiB and more cost a third of 64 KiB buckets
/// on chairs-tiny's tensors (`gdrf-bench allreduce`, README).
pub(crate) const GRADIENT_BUCKET_BYTES: usize = 16 << 20;

impl Trainer {
    /// Makes this trainer rank `group.rank()` of `group`: checks that every stage's batch
    /// splits into equal shares (each a multiple of the stage's `batch_split`, and even
    /// while the mode-seeking pairs are drawn), refuses the options that look across a
    /// batch or draw inside the discriminator (not sharded yet), and copies rank 0's
    /// networks to every rank.
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
        for (key, used) in [
            ("discriminator.augment", !d.augment.is_empty()),
            ("discriminator.minibatch_std_group", d.minibatch_std_group > 0),
            ("loss.coverage_weight", self.cfg.loss.coverage_weight > 0.0),
        ] {
            if used {
                return Err(Error::Config(format!("{key} is not supported with several ranks yet")));
            }
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
}
