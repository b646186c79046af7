"""PyTorch reference of EfficientNet-Lite0 as gdrf-core/src/pretrained/effnet.rs computes it,
written independently from the layout (B0's blocks without squeeze-and-excitation, ReLU6,
TF "same" padding, BatchNorm eps 1e-3), for the cross-check in tests/eval_features.rs.

Usage: efficientnet_ref.py WEIGHTS.safetensors OUTDIR
Writes OUTDIR/case.safetensors: input batches `input_small` (3 images 40×40, upsampled to
224) and `input_large` (2 images 300×300, antialiased down to 224), both in [-1, 1], and for
each the expected `pooled` (B, 1280), `logits` (B, 1000) and `tap{i}` feature maps.
"""
import os
import sys

import torch
import torch.nn as nn
import torch.nn.functional as F
from safetensors.torch import load_file, save_file

STAGES = [(1, 3, 1, 16, 1), (6, 3, 2, 24, 2), (6, 5, 2, 40, 2), (6, 3, 2, 80, 3),
          (6, 5, 1, 112, 3), (6, 5, 2, 192, 4), (6, 3, 1, 320, 1)]
TAPS = [0, 2, 4, 10, 15]


def same_pad(x, k, s):
    def split(n):
        out = -(-n // s)
        total = max((out - 1) * s + k - n, 0)
        return total // 2, total - total // 2
    t, b = split(x.shape[2])
    l, r = split(x.shape[3])
    return F.pad(x, (l, r, t, b))


class ConvBn(nn.Module):
    def __init__(self, cin, cout, k, s, groups, act):
        super().__init__()
        self.conv = nn.Conv2d(cin, cout, k, s, 0, groups=groups, bias=False)
        self.bn = nn.BatchNorm2d(cout, eps=1e-3)
        self.k, self.s, self.act = k, s, act

    def forward(self, x):
        y = self.bn(self.conv(same_pad(x, self.k, self.s)))
        return F.relu6(y) if self.act else y


class Block(nn.Module):
    def __init__(self, cin, cout, ratio, k, s):
        super().__init__()
        mid = cin * ratio
        self.expand = ConvBn(cin, mid, 1, 1, 1, True) if ratio != 1 else None
        self.dw = ConvBn(mid, mid, k, s, mid, True)
        self.project = ConvBn(mid, cout, 1, 1, 1, False)
        self.skip = s == 1 and cin == cout

    def forward(self, x):
        h = self.expand(x) if self.expand is not None else x
        y = self.project(self.dw(h))
        return y + x if self.skip else y


class Lite0(nn.Module):
    def __init__(self):
        super().__init__()
        self.stem = ConvBn(3, 32, 3, 2, 1, True)
        blocks, cin = [], 32
        for ratio, k, s, cout, n in STAGES:
            for r in range(n):
                blocks.append(Block(cin if r == 0 else cout, cout, ratio, k, s if r == 0 else 1))
            cin = cout
        self.blocks = nn.ModuleList(blocks)
        self.head = ConvBn(320, 1280, 1, 1, 1, True)
        self.fc = nn.Linear(1280, 1000)

    def load_release(self, sd):
        """Maps the wheel's `_conv_stem`/`_blocks.N._…` names onto this module."""
        def cb(m, conv, bn):
            m.conv.weight.data.copy_(sd[conv + ".weight"])
            for a in ("weight", "bias", "running_mean", "running_var"):
                getattr(m.bn, a).data.copy_(sd[f"{bn}.{a}"])
        used = 0
        cb(self.stem, "_conv_stem", "_bn0")
        for i, b in enumerate(self.blocks):
            p = f"_blocks.{i}"
            if b.expand is not None:
                cb(b.expand, p + "._expand_conv", p + "._bn0")
            cb(b.dw, p + "._depthwise_conv", p + "._bn1")
            cb(b.project, p + "._project_conv", p + "._bn2")
        cb(self.head, "_conv_head", "_bn1")
        self.fc.weight.data.copy_(sd["_fc.weight"])
        self.fc.bias.data.copy_(sd["_fc.bias"])
        n = sum(t.numel() for t in self.state_dict().values() if t.is_floating_point())
        want = sum(t.numel() for t in sd.values() if t.is_floating_point())
        assert n == want, (n, want)

    def forward(self, x):
        h = self.stem(x)
        taps = []
        for i, b in enumerate(self.blocks):
            h = b(h)
            if i in TAPS:
                taps.append(h)
        pooled = self.head(h).mean((2, 3))
        return pooled, self.fc(pooled), taps


def prepare(x, size=224):
    shrink = x.shape[2] > size or x.shape[3] > size
    return F.interpolate(x, size=(size, size), mode="bilinear", align_corners=False, antialias=shrink)


def main():
    weights, out = sys.argv[1], sys.argv[2]
    torch.manual_seed(0)
    net = Lite0().eval()
    net.load_release(load_file(weights))
    # Smooth images with edges (coarse noise upsampled, plus a hard-edged square), in [-1, 1].
    def images(n, size):
        x = F.interpolate(torch.rand(n, 3, 8, 8) * 2 - 1, size=(size, size), mode="bilinear", align_corners=False)
        x[:, :, size // 4: size // 2, size // 3: size // 2] = 0.9
        return x.clamp(-1, 1)
    case = {"input_small": images(3, 40), "input_large": images(2, 300)}
    with torch.no_grad():
        for name in ("small", "large"):
            pooled, logits, taps = net(prepare(case["input_" + name]))
            case[f"{name}.pooled"] = pooled
            case[f"{name}.logits"] = logits
            for i, t in enumerate(taps):
                case[f"{name}.tap{i}"] = t
    # The LPIPS-style perceptual distance (gdrf-core/src/pretrained/perceptual.rs) between the
    # small inputs and a perturbed copy, and its gradient with respect to the first argument.
    def unit(t):
        return t / (t.pow(2).sum(1, keepdim=True).sqrt() + 1e-10)
    x = case["input_small"].clone().requires_grad_(True)
    y = (case["input_small"] + 0.3 * torch.sin(7 * case["input_small"])).clamp(-1, 1)
    _, _, tx = net(prepare(x))
    _, _, ty = net(prepare(y))
    d = sum((unit(a) - unit(b)).pow(2).sum(1).mean((1, 2)) for a, b in zip(tx, ty)) / len(tx)
    d.sum().backward()
    case["perceptual.y"] = y
    case["perceptual.distance"] = d.detach()
    case["perceptual.grad_x"] = x.grad
    os.makedirs(out, exist_ok=True)
    save_file({k: v.contiguous() for k, v in case.items()}, os.path.join(out, "case.safetensors"))


if __name__ == "__main__":
    main()
