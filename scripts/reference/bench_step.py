#!/usr/bin/env python3
"""Times full training steps of the PyTorch reference (the release's order: D step, then
G step with Adam, gradient clipping and the EMA update) at configurable sizes, and prints
JSON on stdout (progress goes to stderr). `gdrf-bench step` runs it with the settings of
a training config.

    bench_step.py [--resolution 32] [--num-steps 12] [--batch 8] [--batch-split 1]
                  [--latent-dim 64] [--hidden-dim 64] [--mapping-hidden-dim 64]
                  [--disc-channels 16,16,32,48,64,96,128,128,128] [--warmup 1] [--steps 3] ...

Real images are random values in [-1, 1] with random poses (timing does not depend on
them). Timed steps use step indices where R1 is due (multiples of --r1-interval); the
warm-up steps use the indices 0, 1, ….

With --world N the step runs as N ranks of torch.distributed (Gloo over loopback), each
on --batch / N images with --threads threads: every network's gradients are all-reduced
(averaged, in buckets of 16 MiB) after its backward and before clipping, as
DistributedDataParallel does, and the ranks start every step together. Rank 0's timings
are printed, with the time in all-reduces as the "allreduce" phase.
"""
import argparse
import json
import math
import os
import resource
import statistics
import sys
import time

import torch
import torch.distributed as dist
import torch.nn.functional as F

sys.path.insert(0, os.path.dirname(os.path.abspath(__file__)))
import dist_ref  # noqa: E402
import gdrf_ref as ref  # noqa: E402
import losses_ref as L  # noqa: E402


def floats(s):
    return [float(x) for x in s.split(",")]


def ints(s):
    return [int(x) for x in s.split(",")]


def parse():
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    a = ap.add_argument
    a("--resolution", type=int, default=32)
    a("--num-steps", type=int, default=12, help="coarse samples per ray (the importance pass adds as many)")
    a("--batch", type=int, default=8)
    a("--batch-split", type=int, default=1)
    a("--latent-dim", type=int, default=256)
    a("--hidden-dim", type=int, default=256)
    a("--mapping-hidden-dim", type=int, default=256)
    a("--trunk-layers", type=int, default=5)
    a("--color-layers", type=int, default=4)
    a("--deform-layers", type=int, default=4)
    a("--correct-scale", type=float, default=100.0)
    a("--disc-channels", type=ints, default=list(L.CHANNELS), help="9 comma-separated widths")
    a("--r1-gamma", type=float, default=1.0)
    a("--r1-interval", type=int, default=1)
    a("--pose-weight", type=float, default=15.0)
    a("--reg-weights", type=floats, default=[L.REG_WEIGHTS[k] for k in ("correction", "smoothness", "rigidity", "normal")],
      help="correction,smoothness,rigidity,normal")
    a("--reg-variant", choices=["release", "paper"], default="release")
    a("--reg-ray-ratio", type=float, default=0.05)
    a("--reg-near-ratio", type=float, default=0.2)
    a("--reg-sample-ratio", type=float, default=0.05)
    a("--topk-interval", type=float, default=2000.0)
    a("--topk-floor", type=float, default=0.6)
    a("--g-lr", type=float, default=2e-5)
    a("--d-lr", type=float, default=2e-4)
    a("--betas", type=floats, default=[0.0, 0.9])
    a("--adam-eps", type=float, default=1e-8)
    a("--grad-clip", type=float, default=0.3, help="0 = off")
    a("--ema-decay", type=float, default=0.999)
    a("--no-ema-warmup", action="store_true")
    a("--fov", type=float, default=50.0)
    a("--ray-start", type=float, default=0.6)
    a("--ray-end", type=float, default=1.4)
    a("--h-mean", type=float, default=0.0)
    a("--h-std", type=float, default=math.pi)
    a("--v-mean", type=float, default=1.070796)
    a("--v-std", type=float, default=0.2618)
    a("--warmup", type=int, default=1, help="untimed steps first")
    a("--steps", type=int, default=3, help="timed steps")
    a("--threads", type=int, default=os.cpu_count())
    a("--device", default="cpu", help="cpu, cuda or cuda:N (every tensor is created there)")
    a("--bf16", action="store_true", help="bfloat16 autocast around the whole step")
    a("--seed", type=int, default=0)
    a("--world", type=int, default=1, help="ranks of torch.distributed (Gloo over loopback)")
    args = ap.parse_args()
    if args.world < 1 or args.batch % args.world or (args.batch // args.world) % args.batch_split:
        ap.error(f"--world {args.world} must split --batch {args.batch} into shares that --batch-split divides")
    if args.batch_split < 1 or args.batch % args.batch_split:
        ap.error(f"--batch-split {args.batch_split} must divide --batch {args.batch}")
    if len(args.disc_channels) != len(L.CHANNELS):
        ap.error(f"--disc-channels needs {len(L.CHANNELS)} widths")
    if len(args.reg_weights) != 4 or len(args.betas) != 2:
        ap.error("--reg-weights needs 4 values, --betas 2")
    if args.steps < 1:
        ap.error("--steps must be at least 1")
    return args


class Bench:
    def __init__(self, a, rank=0):
        self.a = a
        self.cuda = torch.device(a.device).type == "cuda"
        self.batch = a.batch // a.world  # this rank's share
        self.comm = 0.0  # seconds in all-reduces
        torch.manual_seed(a.seed)  # the same weights on every rank
        self.gen = ref.Generator(a.latent_dim, a.hidden_dim, a.mapping_hidden_dim, trunk=a.trunk_layers,
                                 color=a.color_layers, deform_layers=a.deform_layers, correct_scale=a.correct_scale)
        self.disc = L.Discriminator(a.disc_channels)
        self.g_params = list(self.gen.parameters())
        self.d_params = list(self.disc.parameters())
        betas = tuple(a.betas)
        self.opt_g = torch.optim.Adam(self.g_params, lr=a.g_lr, betas=betas, eps=a.adam_eps)
        self.opt_d = torch.optim.Adam(self.d_params, lr=a.d_lr, betas=betas, eps=a.adam_eps)
        self.ema = [p.detach().clone() for p in self.g_params]
        self.ema_updates = 0
        self.reg_weights = dict(zip(("correction", "smoothness", "rigidity", "normal"), a.reg_weights))
        torch.manual_seed(a.seed + 1 + rank)  # each rank its own draws

    def poses(self, k):
        a = self.a
        pitch = (torch.rand(k, 1) * 2 - 1) * a.v_std + a.v_mean
        yaw = (torch.rand(k, 1) * 2 - 1) * a.h_std + a.h_mean
        return pitch.clamp(1e-5, math.pi - 1e-5), yaw

    def render(self, z, pitch, yaw, **kw):
        a = self.a
        b, r, n = z.shape[0], a.resolution ** 2, a.num_steps
        shape = self.gen.deformnet.siren.mapping_network(z)
        app = self.gen.siren.mapping_network(z)
        out = ref.render(self.gen, shape, app, pitch, yaw, a.resolution, a.fov, a.ray_start, a.ray_end, n,
                         torch.rand(b, r, n), torch.rand(b, r, n), **kw)
        return shape, out

    def reduce(self, params):
        """Averages the gradients over the ranks, bucketed as DistributedDataParallel does."""
        if self.a.world == 1:
            return
        t0 = time.perf_counter()
        grads = [p.grad for p in params if p.grad is not None]
        start = 0
        while start < len(grads):
            end, size = start + 1, grads[start].numel() * grads[start].element_size()
            while end < len(grads) and size + grads[end].numel() * grads[end].element_size() <= 16 << 20:
                size += grads[end].numel() * grads[end].element_size()
                end += 1
            flat = torch.cat([g.reshape(-1) for g in grads[start:end]])
            dist.all_reduce(flat)
            flat /= self.a.world
            off = 0
            for g in grads[start:end]:
                g.copy_(flat[off:off + g.numel()].view_as(g))
                off += g.numel()
            start = end
        self.comm += time.perf_counter() - t0

    def clip(self, params):
        if self.a.grad_clip > 0:
            torch.nn.utils.clip_grad_norm_(params, self.a.grad_clip)

    def d_step(self, step):
        a = self.a
        b = self.batch
        chunk = b // a.batch_split
        z = torch.randn(b, a.latent_dim)
        pitch, yaw = self.poses(b)
        with torch.no_grad():  # the release renders D's fakes in batch_split chunks
            fakes = torch.cat([self.render(z[i:i + chunk], pitch[i:i + chunk], yaw[i:i + chunk])[1][0]
                               for i in range(0, b, chunk)])
        r1_due = a.r1_gamma != 0 and step % a.r1_interval == 0
        real = (torch.rand(b, 3, a.resolution, a.resolution) * 2 - 1).requires_grad_(r1_due)
        real_pitch, real_yaw = self.poses(b)
        lr, _, pr = self.disc(real, 1.0)
        lf, _, pf = self.disc(fakes, 1.0)
        loss = F.softplus(-lr).mean() + F.softplus(lf).mean()
        if r1_due:
            loss = loss + a.r1_gamma * a.r1_interval * L.r1(lr, real)
        loss = loss + a.pose_weight * (L.pose_loss(pf, torch.cat([pitch, yaw], 1))
                                       + L.pose_loss(pr, torch.cat([real_pitch, real_yaw], 1)))
        self.opt_d.zero_grad(set_to_none=True)
        loss.backward()
        self.reduce(self.d_params)
        self.clip(self.d_params)
        self.opt_d.step()
        return loss.item()

    def g_step(self, step):
        a = self.a
        b, split = self.batch, a.batch_split
        chunk = b // split
        r = a.resolution ** 2
        z_all = torch.randn(b, a.latent_dim)
        pitch_all, yaw_all = self.poses(b)
        for p in self.d_params:  # D frozen: no gradients for its parameters
            p.requires_grad_(False)
        self.opt_g.zero_grad(set_to_none=True)
        total = 0.0
        try:
            for c in range(split):
                sl = slice(c * chunk, (c + 1) * chunk)
                z, pitch, yaw = z_all[sl], pitch_all[sl], yaw_all[sl]
                shape, (img, _, _, smp) = self.render(z, pitch, yaw, return_samples=True)
                logit, _, pose = self.disc(img, 1.0)
                k = L.topk_count(step, chunk, a.topk_interval, a.topk_floor)
                loss = L.g_adv(logit, k) + a.pose_weight * L.pose_loss(pose, torch.cat([pitch, yaw], 1))
                if a.reg_variant == "release":
                    ray_idx = torch.randint(r, (chunk, max(L.round_half_up(a.reg_ray_ratio * r), 1)))
                    near, rest = L.select_release(smp, ray_idx, a.reg_near_ratio)
                else:
                    near, rest = L.select_paper(smp, a.reg_sample_ratio)
                reg = L.regularisers(self.gen, shape, near, rest, a.reg_variant)
                loss = loss + sum(self.reg_weights[k_] * v for k_, v in reg.items())
                (loss / split).backward()
                total += loss.item() / split
        finally:
            for p in self.d_params:
                p.requires_grad_(True)
        self.reduce(self.g_params)
        self.clip(self.g_params)
        self.opt_g.step()
        self.ema_update()
        return total

    @torch.no_grad()
    def ema_update(self):
        """torch_ema: decay_n = min(decay, (1 + n)/(10 + n)) at the n-th update (n from 1)."""
        self.ema_updates += 1
        n = self.ema_updates
        d = self.a.ema_decay if self.a.no_ema_warmup else min(self.a.ema_decay, (1 + n) / (10 + n))
        for s, p in zip(self.ema, self.g_params):
            s.sub_((1 - d) * (s - p))

    def sync(self):
        if self.cuda:
            torch.cuda.synchronize()

    def step(self, step):
        dev = torch.device(self.a.device)
        with torch.autocast(dev.type, dtype=torch.bfloat16, enabled=self.a.bf16):
            self.sync()
            t0 = time.perf_counter()
            d = self.d_step(step)
            self.sync()
            t1 = time.perf_counter()
            g = self.g_step(step)
            self.sync()
            t2 = time.perf_counter()
        if not (math.isfinite(d) and math.isfinite(g)):
            print(f"warning: non-finite loss at step {step} (d {d}, g {g})", file=sys.stderr)
        return t1 - t0, t2 - t1, t2 - t0


def measure(a, rank=0):
    """Warm-up and timed steps; returns the printed JSON's fields."""
    bench = Bench(a, rank)
    samples = {"step": [], "d_step": [], "g_step": [], "allreduce": []}
    say = (lambda m: print(m, file=sys.stderr)) if rank == 0 else (lambda m: None)
    for i in range(a.warmup):
        if a.world > 1:
            dist.barrier()
        _, _, s = bench.step(i)
        say(f"reference warm-up step {i}: {s:.2f} s")
    # Timed steps at indices where R1 is due (every step when r1_interval is 1).
    first = -(-a.warmup // a.r1_interval) * a.r1_interval
    for i in range(a.steps):
        idx = first + i * a.r1_interval
        if a.world > 1:
            dist.barrier()
        comm = bench.comm
        d, g, s = bench.step(idx)
        samples["d_step"].append(d)
        samples["g_step"].append(g)
        samples["step"].append(s)
        samples["allreduce"].append(bench.comm - comm)
        say(f"reference step {idx}: {s:.2f} s (D {d:.2f} s, G {g:.2f} s)")
    med = {k: statistics.median(v) for k, v in samples.items()}
    return dict(implementation="PyTorch reference", torch=torch.__version__, threads=a.threads, world=a.world,
                median_s=med, samples_s=samples,
                peak_rss_mb=resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024,
                peak_gpu_mb=torch.cuda.max_memory_allocated() / 2**20 if bench.cuda else None,
                images_per_second=a.batch / med["step"])


def rank_main(rank, a, port, q):
    torch.set_num_threads(a.threads)
    torch.set_default_device(a.device)
    dist.init_process_group("gloo", init_method=f"tcp://127.0.0.1:{port}", rank=rank, world_size=a.world)
    out = measure(a, rank)
    if rank == 0:
        q.put(out)
    dist_ref.finish(q)


def main():
    a = parse()
    if a.world == 1:
        torch.set_num_threads(a.threads)
        torch.set_default_device(a.device)
        print(json.dumps(measure(a)))
        return
    out = dist_ref.spawn(a.world, rank_main, a)
    print(json.dumps(out))


if __name__ == "__main__":
    main()
