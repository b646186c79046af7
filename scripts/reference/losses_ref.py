"""PyTorch reference of the discriminator and the training losses, written from the
reference specification (sections 3 and 4). Names follow the authors' release."""
import math

import torch
import torch.nn as nn
import torch.nn.functional as F

CHANNELS = [16, 32, 64, 128, 256, 400, 400, 400, 400]
START = {2: 8, 4: 7, 8: 6, 16: 5, 32: 4, 64: 3, 128: 2, 256: 1, 512: 0}


class AddCoords(nn.Module):
    def forward(self, x):
        b, _, h, w = x.shape
        rows = (torch.arange(h, dtype=x.dtype) / (h - 1) * 2 - 1).view(1, 1, h, 1).expand(b, 1, h, w)
        cols = (torch.arange(w, dtype=x.dtype) / (w - 1) * 2 - 1).view(1, 1, 1, w).expand(b, 1, h, w)
        return torch.cat([x, rows, cols], 1)


class CoordConv(nn.Module):
    def __init__(self, cin, cout, k, padding):
        super().__init__()
        self.addcoords = AddCoords()
        self.conv = nn.Conv2d(cin + 2, cout, k, padding=padding)

    def forward(self, x):
        return self.conv(self.addcoords(x))


class ResidualCoordConvBlock(nn.Module):
    def __init__(self, cin, cout):
        super().__init__()
        self.network = nn.Sequential(CoordConv(cin, cout, 3, 1), nn.LeakyReLU(0.2),
                                     CoordConv(cout, cout, 3, 1), nn.LeakyReLU(0.2))
        self.proj = nn.Conv2d(cin, cout, 1) if cin != cout else None

    def forward(self, x):
        y = F.avg_pool2d(self.network(x), 2)
        identity = F.avg_pool2d(x, 2)
        if self.proj is not None:
            identity = self.proj(identity)
        return (y + identity) / math.sqrt(2)


class AdapterBlock(nn.Module):
    def __init__(self, c):
        super().__init__()
        self.model = nn.Sequential(nn.Conv2d(3, c, 1, padding=0), nn.LeakyReLU(0.2))

    def forward(self, x):
        return self.model(x)


def downsample_aa(x):
    c = x.shape[1]
    k1 = torch.tensor([1, 3, 3, 1], dtype=x.dtype) / 8
    k = (k1[:, None] * k1[None, :]).expand(c, 1, 4, 4)
    return F.conv2d(F.pad(x, (1, 1, 1, 1), mode="replicate"), k, stride=2, groups=c)


class Discriminator(nn.Module):
    """ProgressiveEncoderDiscriminatorAntiAlias."""

    def __init__(self, channels=None):
        """channels: the 9 widths of fromRGB[i] / the input of layers[i] (default CHANNELS)."""
        super().__init__()
        ch = list(CHANNELS if channels is None else channels)
        assert len(ch) == len(CHANNELS), f"channels needs {len(CHANNELS)} widths, got {ch}"
        self.layers = nn.ModuleList([ResidualCoordConvBlock(ch[i], ch[i + 1]) for i in range(8)])
        self.fromRGB = nn.ModuleList([AdapterBlock(c) for c in ch])
        self.final_layer = nn.Conv2d(ch[-1], 1 + 256 + 2, 2)

    def forward(self, img, alpha):
        start = START[img.shape[-1]]
        x = self.fromRGB[start](img)
        for i, layer in enumerate(self.layers[start:]):
            if i == 1:
                x = alpha * x + (1 - alpha) * self.fromRGB[start + 1](downsample_aa(img))
            x = layer(x)
        x = self.final_layer(x).reshape(x.shape[0], -1)
        return x[:, 0:1], x[:, 1:257], x[:, 257:259]


def disc_name_to_gdrf(name):
    p = name.split(".")
    if p[0] == "final_layer":
        return "head." + p[1]
    if p[0] == "fromRGB":
        return f"from_rgb.{p[1]}.{p[-1]}"
    if p[2] == "proj":
        return f"layers.{p[1]}.proj.{p[-1]}"
    return f"layers.{p[1]}.conv{1 if p[3] == '0' else 2}.{p[-1]}"


# ----------------------------------------------------------------------------- GAN terms

def topk_count(step, n, interval=2000.0, floor=0.6):
    p = max(0.99 ** (step / interval), floor)
    return min(max(math.ceil(p * n), 1), n)


def g_adv(logit, k):
    return F.softplus(-torch.topk(logit.view(-1), k).values).mean()


def pose_loss(pred, target):
    return (1 - torch.cos(pred - target)).mean()


def r1(logit, real):
    g = torch.autograd.grad(logit.sum(), real, create_graph=True)[0]
    return 0.5 * (g.view(g.shape[0], -1).norm(2, dim=1) ** 2).mean()


# ----------------------------------------------------------------------------- regularisers

def round_half_up(x):
    return int(math.floor(x + 0.5))


def select_release(s, ray_idx, near_ratio=0.2):
    """s: render samples (z (B,R,S), depth (B,R,1), origins/dirs (B,R,3)) → near, rest points."""
    z, depth, o, d = s["z"].detach(), s["depth"].detach(), s["origins"], s["dirs"]
    b, n = ray_idx.shape
    S = z.shape[-1]
    pts = (o.unsqueeze(2) + d.unsqueeze(2) * z.unsqueeze(-1)).detach()
    z_sel = torch.gather(z, 1, ray_idx.unsqueeze(-1).expand(b, n, S))
    d_sel = torch.gather(depth, 1, ray_idx.unsqueeze(-1))
    p_sel = torch.gather(pts, 1, ray_idx.view(b, n, 1, 1).expand(b, n, S, 3))
    order = torch.argsort((z_sel - d_sel).abs(), -1)
    k = min(max(round_half_up(near_ratio * S), 1), S)

    def take(o_):
        return torch.gather(p_sel, 2, o_.unsqueeze(-1).expand(-1, -1, -1, 3)).reshape(b, -1, 3)
    return take(order[..., :k]), take(order[..., k:])


def select_paper(s, ratio=0.05):
    z, depth, o, d = s["z"].detach(), s["depth"].detach(), s["origins"], s["dirs"]
    b, r, S = z.shape
    pts = (o.unsqueeze(2) + d.unsqueeze(2) * z.unsqueeze(-1)).detach().reshape(b, r * S, 3)
    k = min(max(round_half_up(ratio * r * S), 1), r * S)
    idx = torch.topk((z - depth).abs().reshape(b, r * S), k, dim=1, largest=False).indices
    return torch.gather(pts, 1, idx.unsqueeze(-1).expand(b, k, 3)), None


def regularisers(gen, shape, near, rest, variant="release"):
    x = (near if rest is None else torch.cat([near, rest], 1)).detach().requires_grad_(True)
    b, p = x.shape[:2]
    pn = near.shape[1]
    dx, dsigma = gen.deformnet(x, *shape)
    jac = torch.stack([torch.autograd.grad(dx[..., i].sum(), x, create_graph=True)[0] for i in range(3)], 2)
    eye = torch.eye(3, dtype=x.dtype)
    j = jac + eye
    strain = j.transpose(-1, -2) @ j - eye
    x_t = x[:, :pn] + dx[:, :pn]
    _, sigma_t = gen.siren.density(x_t)
    sigma = sigma_t + dsigma[:, :pn]
    grad_t = torch.autograd.grad(sigma_t.sum(), x_t, create_graph=True)[0]
    grad = torch.autograd.grad(sigma.sum(), x, retain_graph=True)[0][:, :pn].detach()
    cos_dist = 1 - F.cosine_similarity(grad_t, grad, dim=-1, eps=1e-8)
    if variant == "release":
        return dict(correction=dsigma.abs().mean(),
                    smoothness=torch.linalg.vector_norm(jac, dim=-1).mean(),
                    rigidity=0.5 * torch.linalg.vector_norm(strain.reshape(b, p, 9), dim=-1).mean(),
                    normal=cos_dist.mean())
    return dict(correction=dsigma.abs().sum() / b,
                smoothness=torch.linalg.vector_norm(jac.reshape(b, p, 9), dim=-1).sum() / b,
                rigidity=torch.linalg.vector_norm(strain.reshape(b, p, 9), dim=-1).sum() / b,
                normal=cos_dist.sum() / b)


REG_WEIGHTS = dict(correction=1e-2, smoothness=1.0, rigidity=0.1, normal=5.0)
