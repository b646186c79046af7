"""PyTorch reference of gdrf-core/src/eval/fidelity.rs: PSNR and SSIM as pytorch-msssim's
`ssim(..., data_range=1, size_average=False, win_size=11, win_sigma=1.5, K=(0.01, 0.03))`
computes them (a separable Gaussian window applied with valid convolutions, population
statistics, the map averaged over positions and channels), written here from that recipe.

Usage: fidelity_ref.py IN.safetensors OUT.safetensors
IN holds `a`, `b` (B, 3, H, W) in [-1, 1]; OUT gets `psnr`, `ssim` (B,) in float64.
"""
import sys

import torch
import torch.nn.functional as F
from safetensors.torch import load_file, save_file


def gaussian(size=11, sigma=1.5):
    coords = torch.arange(size, dtype=torch.float64) - size // 2
    g = torch.exp(-(coords ** 2) / (2 * sigma ** 2))
    return g / g.sum()


def ssim(x, y):
    c = x.shape[1]
    g = gaussian()
    win_h = g.view(1, 1, 1, -1).repeat(c, 1, 1, 1)
    win_v = g.view(1, 1, -1, 1).repeat(c, 1, 1, 1)

    def filt(t):
        return F.conv2d(F.conv2d(t, win_h, groups=c), win_v, groups=c)

    mu1, mu2 = filt(x), filt(y)
    s11 = filt(x * x) - mu1 ** 2
    s22 = filt(y * y) - mu2 ** 2
    s12 = filt(x * y) - mu1 * mu2
    c1, c2 = 0.01 ** 2, 0.03 ** 2
    cs = (2 * s12 + c2) / (s11 + s22 + c2)
    lum = (2 * mu1 * mu2 + c1) / (mu1 ** 2 + mu2 ** 2 + c1)
    return (lum * cs).flatten(1).mean(-1)


def main():
    t = load_file(sys.argv[1])
    x = (t["a"].double() + 1) / 2
    y = (t["b"].double() + 1) / 2
    mse = ((x - y) ** 2).flatten(1).mean(-1).clamp_min(1e-10)
    save_file({"psnr": -10 * torch.log10(mse), "ssim": ssim(x, y)}, sys.argv[2])


if __name__ == "__main__":
    main()
