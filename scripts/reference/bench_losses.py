#!/usr/bin/env python3
"""Times one generator loss + backward and one discriminator loss + backward of the
PyTorch reference (release settings: regularisers on, R1 every step), and prints JSON.

    bench_losses.py [--batch 4] [--batch-split 4] [--resolution 64] [--steps 36] [--repeats 1]
"""
import argparse
import json
import os
import resource
import statistics
import sys
import time

import torch
import torch.nn.functional as F

sys.path.insert(0, os.path.dirname(os.path.abspath(__file__)))
import gdrf_ref as ref  # noqa: E402
import losses_ref as L  # noqa: E402

FOV, START, END = 50.0, 0.6, 1.4


def main():
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--batch", type=int, default=4)
    ap.add_argument("--batch-split", type=int, default=4)
    ap.add_argument("--resolution", type=int, default=64)
    ap.add_argument("--steps", type=int, default=36)
    ap.add_argument("--repeats", type=int, default=1)
    ap.add_argument("--threads", type=int, default=os.cpu_count())
    a = ap.parse_args()
    torch.set_num_threads(a.threads)
    torch.manual_seed(0)
    gen, disc = ref.Generator(), L.Discriminator()
    res, n, b = a.resolution, a.steps, a.batch
    r = res * res
    chunk = b // a.batch_split
    times = {"g_forward": [], "g_backward": [], "d_forward": [], "d_backward": []}

    def poses(k):
        return (torch.rand(k, 1) * 2 - 1) * 0.2618 + 1.070796, (torch.rand(k, 1) * 2 - 1) * 3.141592653589793

    for rep in range(a.repeats + 1):  # the first pass, at 16² and untimed, warms up
        if rep == 0:
            res, n = 16, 8
            r = res * res
        else:
            res, n = a.resolution, a.steps
            r = res * res
        gen.zero_grad()
        disc.zero_grad()
        fwd = bwd = 0.0
        for _ in range(a.batch_split):
            t0 = time.perf_counter()
            z = torch.randn(chunk, 256)
            pitch, yaw = poses(chunk)
            shape = gen.deformnet.siren.mapping_network(z)
            app = gen.siren.mapping_network(z)
            img, _, _, smp = ref.render(gen, shape, app, pitch, yaw, res, FOV, START, END, n,
                                        torch.rand(chunk, r, n), torch.rand(chunk, r, n), return_samples=True)
            logit, _, pose = disc(img, 1.0)
            loss = L.g_adv(logit, L.topk_count(0, chunk)) + 15 * L.pose_loss(pose, torch.cat([pitch, yaw], 1))
            ray_idx = torch.randint(r, (chunk, L.round_half_up(0.05 * r)))
            near, rest = L.select_release(smp, ray_idx)
            reg = L.regularisers(gen, shape, near, rest)
            loss = loss + sum(L.REG_WEIGHTS[k] * v for k, v in reg.items())
            t1 = time.perf_counter()
            loss.backward()
            t2 = time.perf_counter()
            fwd += t1 - t0
            bwd += t2 - t1
        if rep > 0:
            times["g_forward"].append(fwd)
            times["g_backward"].append(bwd)

        disc.zero_grad()
        t0 = time.perf_counter()
        z = torch.randn(b, 256)
        pitch, yaw = poses(b)
        with torch.no_grad():
            fakes = torch.cat([ref.render(gen, gen.deformnet.siren.mapping_network(z[i:i + chunk]),
                                          gen.siren.mapping_network(z[i:i + chunk]), pitch[i:i + chunk], yaw[i:i + chunk],
                                          res, FOV, START, END, n, torch.rand(chunk, r, n), torch.rand(chunk, r, n))[0]
                               for i in range(0, b, chunk)])
        real = (torch.rand(b, 3, res, res) * 2 - 1).requires_grad_(True)
        lr, _, pr = disc(real, 1.0)
        lf, _, pf = disc(fakes, 1.0)
        loss = (F.softplus(-lr).mean() + F.softplus(lf).mean() + L.r1(lr, real)
                + 15 * (L.pose_loss(pf, torch.cat([pitch, yaw], 1)) + L.pose_loss(pr, torch.cat(poses(b), 1))))
        t1 = time.perf_counter()
        loss.backward()
        t2 = time.perf_counter()
        if rep > 0:
            times["d_forward"].append(t1 - t0)
            times["d_backward"].append(t2 - t1)

    med = {k: statistics.median(v) for k, v in times.items()}
    print(json.dumps(dict(implementation="pytorch-reference", torch=torch.__version__, threads=a.threads,
                          median_s=med, samples_s=times,
                          peak_rss_mb=resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024)))


if __name__ == "__main__":
    main()
