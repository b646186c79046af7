"""numpy/scipy reference of the feature distances in gdrf-core/src/eval/distance.rs.

Usage: distance_ref.py IN.safetensors OUT.safetensors
IN holds float64 features `a` (n, d), `b` (m, d) and int64 subset indices `subsets_a`,
`subsets_b` (S, k). OUT gets `fd`: the Fréchet distance exactly as pytorch-fid's
`calculate_frechet_distance` computes it (np.cov, scipy.linalg.sqrtm of the product, the
eps offset when it is singular, the real part), and `kid`: the unbiased MMD² with the
cubic polynomial kernel on each subset pair, as clean-fid / torch-fidelity compute it.
"""
import sys

import numpy as np
import torch
from safetensors.torch import load_file, save_file
from scipy import linalg


def frechet(mu1, sigma1, mu2, sigma2, eps=1e-6):
    # pytorch_fid.fid_score.calculate_frechet_distance, verbatim in substance.
    diff = mu1 - mu2
    covmean, _ = linalg.sqrtm(sigma1.dot(sigma2), disp=False)
    if not np.isfinite(covmean).all():
        offset = np.eye(sigma1.shape[0]) * eps
        covmean = linalg.sqrtm((sigma1 + offset).dot(sigma2 + offset))
    if np.iscomplexobj(covmean):
        if not np.allclose(np.diagonal(covmean).imag, 0, atol=1e-3):
            raise ValueError("imaginary component %g" % np.max(np.abs(covmean.imag)))
        covmean = covmean.real
    return diff.dot(diff) + np.trace(sigma1) + np.trace(sigma2) - 2 * np.trace(covmean)


def mmd2(x, y):
    m, d = x.shape
    a = (x @ x.T / d + 1) ** 3 + (y @ y.T / d + 1) ** 3
    b = (x @ y.T / d + 1) ** 3
    return ((a.sum() - np.diag(a).sum()) / (m - 1) - b.sum() * 2 / m) / m


def main():
    t = {k: v.numpy() for k, v in load_file(sys.argv[1]).items()}
    a, b = t["a"], t["b"]
    fd = frechet(a.mean(0), np.cov(a, rowvar=False), b.mean(0), np.cov(b, rowvar=False))
    kid = [mmd2(a[ia], b[ib]) for ia, ib in zip(t["subsets_a"], t["subsets_b"])]
    save_file({"fd": torch.tensor([fd], dtype=torch.float64),
               "kid": torch.tensor(kid, dtype=torch.float64)}, sys.argv[2])


if __name__ == "__main__":
    main()
