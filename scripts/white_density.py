#!/usr/bin/env python3
"""Hidden geometry: how much of a generator's density is painted the background's white.

Density depends only on the shape code, so a silhouette should not change when only the
appearance code does. But on a white background a generator can paint part of its density
white, where it is invisible, and another appearance code can paint the same density in a
colour that shows: a swivel base becomes a pedestal. The probe then reads another structure,
and the structure swap test fails for a reason it cannot see.

For each checkpoint this renders CODES random codes at random poses of the checkpoint's
camera (the PyTorch reference renderer: N + N samples per ray, no jitter) and reports, as
one JSON line each:

- opaque_area: the share of pixels whose opacity in front of the far plane (the weights of
  every sample but the last, which the release's delta_final of 1e10 makes opaque on every
  ray: it paints the background, white for a generator trained on random backgrounds, as
  gdrf's renderer paints it) exceeds 0.5;
- white_of_opaque: the share of those pixels whose colour is near white (every channel above
  --threshold): density that looks like background;
- white_flips_under_swap: the share of opaque pixels that are white under one appearance code
  and not under another (each code's shape with the next code's appearance): silhouette
  that follows the appearance code;
- fog: the mean opacity in front of the far plane of the pixels that are not opaque (at
  most 0.5): thin density over the background, which tints it;
- tint: how far those pixels' colour is from the background's white (the mean over them
  and the channels of 1 - rgb): the fog as it shows. Fog painted white does not show on
  white, fog in the object's colour does.

With --dataset, the same shares of the dataset's images (its alpha channel as the opacity,
the colour composited on white, both resized to the render resolution) come first, as the
real end.

With --figure, the last checkpoint's first 8 codes (at 64², enlarged twice) are drawn in a
PNG: the renders above, their opacity in front of the far plane below (black empty, white
opaque), with the opaque pixels painted near white marked red.

    white_density.py CHECKPOINT... [--codes 64] [--resolution 32] [--samples 12]
                     [--threshold 0.9] [--seed 1234] [--dataset data/chairs-64 [--images 2000]]
                     [--figure FILE.png]
"""
import argparse
import glob
import json
import os
import sys

import numpy as np
import torch

sys.path.insert(0, os.path.join(os.path.dirname(os.path.abspath(__file__)), "reference"))
import gdrf_ref as ref  # noqa: E402
from bench_render import load  # noqa: E402


def render(gen, shape, app, pitch, yaw, res, cam, n):
    """The reference render in [0, 1] `(B, 3, res, res)` and its opacity in front of the far
    plane `(B, res, res)`: the weights of every sample but the last."""
    b = pitch.shape[0]
    u = ((torch.arange(n, dtype=torch.float32) + 0.5) / n).expand(b, res * res, n)
    img, _, _, samples = ref.render(gen, shape, app, pitch, yaw, res, cam["fov_deg"], cam["ray_start"],
                                    cam["ray_end"], n, None, u, return_samples=True,
                                    force_last_white=gen.force_last_white)
    front = samples["weights"][..., :-1, :].sum((-2, -1))
    return (img + 1) / 2, front.reshape(b, res, res)


def poses(cam, k, g):
    """k (pitch, yaw) pairs from the camera's pose distribution (uniform or normal)."""
    if cam["distribution"] == "uniform":
        draw = lambda: torch.rand(k, 1, generator=g) * 2 - 1  # noqa: E731
    elif cam["distribution"] == "normal":
        draw = lambda: torch.randn(k, 1, generator=g)  # noqa: E731
    else:
        sys.exit(f"white_density.py: the camera's {cam['distribution']} pose distribution is not supported")
    yaw = cam["h_mean"] + draw() * cam["h_std"]
    return cam["v_mean"] + draw() * cam["v_std"], yaw


def shares(rgb, opacity, threshold):
    """rgb (B, 3, H, W) in [0, 1], opacity (B, H, W) → (opaque mask, white-and-opaque mask)."""
    opaque = opacity > 0.5
    return opaque, opaque & (rgb.min(1).values > threshold)


def real_end(dataset, res, threshold, limit):
    from PIL import Image
    files = sorted(glob.glob(os.path.join(dataset, "images", "*.png")))[:limit]
    if not files:
        sys.exit(f"white_density.py: no images in {dataset}/images")
    opaque = white = total = 0
    fog, tint = [], []
    for f in files:
        a = np.asarray(Image.open(f).convert("RGBA").resize((res, res), Image.BILINEAR), np.float32) / 255
        alpha = a[..., 3]
        if alpha.min() == 1.0 and f == files[0]:
            print(f"white_density.py: {f} has no transparent pixel; is the alpha channel kept?", file=sys.stderr)
        rgb = a[..., :3] * alpha[..., None] + (1 - alpha[..., None])
        o = alpha > 0.5
        fog.append(alpha[~o])
        tint.append((1 - rgb[~o]).mean(-1))
        opaque += o.sum()
        white += (o & (rgb.min(-1) > threshold)).sum()
        total += o.size
    return {"source": dataset, "images": len(files), "opaque_area": float(opaque / total),
            "white_of_opaque": float(white / max(1, opaque)), "fog": float(np.concatenate(fog).mean()),
            "tint": float(np.concatenate(tint).mean())}


def figure(path, gen, cam, z, pitch, yaw, samples, threshold):
    """Renders (top) and front opacity with near-white opaque pixels in red (bottom), atomically."""
    from PIL import Image
    with torch.no_grad():
        rgb, op = render(gen, gen.deformnet.siren.mapping_network(z), gen.siren.mapping_network(z),
                         pitch, yaw, 64, cam, samples)
    _, white = shares(rgb, op, threshold)
    top = rgb.permute(0, 2, 3, 1).clamp(0, 1).numpy()
    bottom = np.repeat(op.clamp(0, 1).numpy()[..., None], 3, -1)
    bottom[white.numpy()] = (1.0, 0.0, 0.0)
    img = np.concatenate([np.concatenate(list(top), 1), np.concatenate(list(bottom), 1)], 0)
    img = Image.fromarray((img * 255).round().astype(np.uint8))
    tmp = f"{path}.tmp.{os.getpid()}.png"
    img.resize((img.width * 2, img.height * 2), Image.NEAREST).save(tmp)
    os.replace(tmp, path)


def main():
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("checkpoints", nargs="+")
    ap.add_argument("--codes", type=int, default=64)
    ap.add_argument("--resolution", type=int, default=32)
    ap.add_argument("--samples", type=int, default=12, help="coarse samples per ray (as many importance samples)")
    ap.add_argument("--threshold", type=float, default=0.9)
    ap.add_argument("--seed", type=int, default=1234)
    ap.add_argument("--dataset")
    ap.add_argument("--images", type=int, default=2000)
    ap.add_argument("--figure", help="PNG of the last checkpoint's first 8 codes (see above)")
    a = ap.parse_args()
    for flag, value, least in [("--codes", a.codes, 2), ("--resolution", a.resolution, 1),
                               ("--samples", a.samples, 2), ("--images", a.images, 1)]:
        if value < least:
            ap.error(f"{flag} is {value}, expected at least {least}")
    for path in a.checkpoints:
        if not os.path.isfile(path):
            ap.error(f"checkpoint {path} does not exist")
    if a.dataset:
        print(json.dumps(real_end(a.dataset, a.resolution, a.threshold, a.images)), flush=True)
    for path in a.checkpoints:
        gen, header = load(path)
        cam, latent = header["camera"], header["generator"]["latent_dim"]
        g = torch.Generator().manual_seed(a.seed)
        with torch.no_grad():
            z = torch.randn(a.codes, latent, generator=g)
            shape, app = gen.deformnet.siren.mapping_network(z), gen.siren.mapping_network(z)
            pitch, yaw = poses(cam, a.codes, g)
            rgb, op = render(gen, shape, app, pitch, yaw, a.resolution, cam, a.samples)
            other = tuple(t.roll(1, 0) for t in app)
            rgb2, op2 = render(gen, shape, other, pitch, yaw, a.resolution, cam, a.samples)
        opaque, white = shares(rgb, op, a.threshold)
        _, white2 = shares(rgb2, op2, a.threshold)
        n = max(1, int(opaque.sum()))
        print(json.dumps({"source": path, "step": header.get("info", {}).get("step"), "codes": a.codes,
                          "opaque_area": float(opaque.float().mean()),
                          "white_of_opaque": int(white.sum()) / n,
                          "white_flips_under_swap": int((white ^ white2).sum()) / n,
                          "fog": float(op[~opaque].mean()),
                          "tint": float((1 - rgb.clamp(0, 1)).mean(1)[~opaque].mean())}), flush=True)
    if a.figure:
        k = min(8, a.codes)
        figure(a.figure, gen, cam, z[:k], pitch[:k], yaw[:k], a.samples, a.threshold)


if __name__ == "__main__":
    main()
