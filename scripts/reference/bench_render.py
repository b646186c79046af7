#!/usr/bin/env python3
"""Times the PyTorch reference renderer (the release's sampler: N stratified + N importance
samples through the whole network) on a gdrf generator checkpoint, and prints JSON on
stdout (progress on stderr). `gdrf-edit bench` runs it beside its own configurations.

    bench_render.py CHECKPOINT --seeds 0,1 --poses P1:Y1,P2:Y2 --resolution 64 --num-steps 36
                    [--chunk-points 16384] [--repeats 3] [--warmup 1] [--images-out FILE]

Codes: z = randn(1, latent) after manual_seed(seed). No jitter; the importance uniforms are
(k + 0.5)/N, as the Rust benchmark uses, so both render the same image. Rays are rendered
in chunks of about --chunk-points samples (the Rust renderer's default), all without
gradients. --images-out writes the images (seed-major, then pose) as safetensors.
"""
import argparse
import json
import os
import statistics
import sys
import time

import torch
from safetensors import safe_open
from safetensors.torch import save_file

sys.path.insert(0, os.path.dirname(os.path.abspath(__file__)))
import gdrf_ref as ref  # noqa: E402
from names import release_parameter_order, release_to_gdrf  # noqa: E402


def load(path):
    with safe_open(path, "pt") as f:
        header = json.loads(f.metadata()["gdrf"])
        tensors = {k: f.get_tensor(k) for k in f.keys()}
    g = header["generator"]
    if g.get("deform_scale", 1.0) != 1.0:
        sys.exit("bench_render.py: the reference has no deform_scale other than 1")
    gen = ref.Generator(z_dim=g["latent_dim"], hidden_dim=g["hidden_dim"], map_hidden=g["mapping_hidden_dim"],
                        trunk=g["trunk_layers"], color=g["color_layers"], deform_layers=g["deform_layers"],
                        correct_scale=g["correct_scale"])
    names = release_parameter_order(g["trunk_layers"], g["color_layers"], g["deform_layers"])
    state = {n: tensors[release_to_gdrf(n)] for n in names}
    gen.load_state_dict(state)
    # A generator trained on random backgrounds (generator.background = "random" or
    # "corners") does not paint its background: gdrf's renderer paints each ray's last
    # sample white for it.
    gen.force_last_white = g.get("background", "learned") != "learned"
    return gen.eval(), header


def render(gen, shape, app, pitch, yaw, res, cam, n, chunk_points):
    origins, dirs = ref.world_rays(pitch, yaw, res, cam["fov_deg"])
    r = res * res
    u = ((torch.arange(n, dtype=torch.float32) + 0.5) / n).expand(1, n)
    chunk = max(1, chunk_points // (2 * n))
    pixels, opacities = [], []
    for s in range(0, r, chunk):
        o, d = origins[:, s:s + chunk], dirs[:, s:s + chunk]
        k = o.shape[1]
        z_c = ref.stratified(1, k, n, cam["ray_start"], cam["ray_end"], None, torch.float32)

        def query(z):
            pts = (o.unsqueeze(2) + d.unsqueeze(2) * z.unsqueeze(-1)).reshape(1, -1, 3)
            dd = d.unsqueeze(2).expand(-1, -1, z.shape[2], -1).reshape(1, -1, 3)
            rgb, sigma, *_ = gen.field(pts, dd, shape, app)
            return rgb.reshape(1, k, -1, 3), sigma.reshape(1, k, -1, 1)

        rgb_c, sigma_c = query(z_c)
        _, _, w, _ = ref.integrate(rgb_c, sigma_c, z_c.unsqueeze(-1))
        z_f = ref.importance(z_c.reshape(k, n), w.reshape(k, n), u.expand(k, n)).reshape(1, k, n)
        rgb_f, sigma_f = query(z_f)
        z_all, idx = torch.sort(torch.cat([z_f, z_c], -1), -1)
        rgb = torch.gather(torch.cat([rgb_f, rgb_c], -2), 2, idx.unsqueeze(-1).expand(-1, -1, -1, 3))
        sigma = torch.gather(torch.cat([sigma_f, sigma_c], -2), 2, idx.unsqueeze(-1))
        pixel, _, _, opacity = ref.integrate(rgb, sigma, z_all.unsqueeze(-1), force_last_white=gen.force_last_white)
        pixels.append(pixel)
        opacities.append(opacity)
    return torch.cat(pixels, 1).reshape(res, res, 3).permute(2, 0, 1) * 2 - 1


def main():
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("checkpoint")
    ap.add_argument("--seeds", required=True)
    ap.add_argument("--poses", required=True, help="pitch:yaw pairs in radians, comma separated")
    ap.add_argument("--resolution", type=int, required=True)
    ap.add_argument("--num-steps", type=int, required=True)
    ap.add_argument("--chunk-points", type=int, default=16384)
    ap.add_argument("--repeats", type=int, default=3)
    ap.add_argument("--warmup", type=int, default=1)
    ap.add_argument("--images-out")
    a = ap.parse_args()
    gen, header = load(a.checkpoint)
    cam = header["camera"]
    latent = header["generator"]["latent_dim"]
    seeds = [int(s) for s in a.seeds.split(",")]
    poses = [tuple(float(v) for v in p.split(":")) for p in a.poses.split(",")]
    images = []
    times = []
    with torch.no_grad():
        lat = []
        for s in seeds:
            torch.manual_seed(s)
            z = torch.randn(1, latent)
            lat.append((gen.deformnet.siren.mapping_network(z), gen.siren.mapping_network(z)))
        for rep in range(a.warmup + a.repeats):
            t0 = time.perf_counter()
            out = []
            for shape, app in lat:
                for pitch, yaw in poses:
                    p, y = torch.tensor([[pitch]]), torch.tensor([[yaw]])
                    out.append(render(gen, shape, app, p, y, a.resolution, cam, a.num_steps, a.chunk_points))
            dt = time.perf_counter() - t0
            if rep >= a.warmup:
                times.append(dt / len(out))
            images = out
            print(f"  pytorch {a.resolution}² N={a.num_steps}: {1000 * dt / len(out):.0f} ms/image", file=sys.stderr)
    if a.images_out:
        save_file({"images": torch.stack(images).contiguous()}, a.images_out)
    json.dump({
        "implementation": "pytorch",
        "torch": torch.__version__,
        "threads": torch.get_num_threads(),
        "ms_per_image": 1000 * statistics.median(times),
        "ms_per_image_runs": [1000 * t for t in times],
    }, sys.stdout)


if __name__ == "__main__":
    main()
