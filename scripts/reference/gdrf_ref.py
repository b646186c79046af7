"""A compact PyTorch reference of the GDRF generator and renderer, written from the
reference specification (networks, init, cameras, samplers, integration). Module and
parameter names follow the authors' release so that its state dicts load unchanged.

Everything random can be given explicitly (stratified jitter, importance uniforms), which
is what the cross-check tests use.
"""
import math

import torch
import torch.nn as nn
import torch.nn.functional as F


# ----------------------------------------------------------------------------- init

def frequency_init(freq):
    def init(m):
        if isinstance(m, nn.Linear):
            n = m.weight.size(-1)
            with torch.no_grad():
                m.weight.uniform_(-math.sqrt(6 / n) / freq, math.sqrt(6 / n) / freq)
    return init


def first_layer_sine_init(m):
    if isinstance(m, nn.Linear):
        n = m.weight.size(-1)
        with torch.no_grad():
            m.weight.uniform_(-1 / n, 1 / n)


def kaiming_leaky_init(m):
    if isinstance(m, nn.Linear):
        nn.init.kaiming_normal_(m.weight, a=0.2, mode="fan_in", nonlinearity="leaky_relu")


# ----------------------------------------------------------------------------- layers

class FiLMLayer(nn.Module):
    def __init__(self, input_dim, hidden_dim):
        super().__init__()
        self.layer = nn.Linear(input_dim, hidden_dim)

    def forward(self, x, freq, phase_shift):
        x = self.layer(x)
        freq = freq.unsqueeze(1).expand_as(x)
        phase_shift = phase_shift.unsqueeze(1).expand_as(x)
        return torch.sin(freq * x + phase_shift)


class SINLayer(nn.Module):
    def __init__(self, input_dim, hidden_dim):
        super().__init__()
        self.layer = nn.Linear(input_dim, hidden_dim)

    def forward(self, x):
        return torch.sin(30 * self.layer(x))


class CustomMappingNetwork(nn.Module):
    def __init__(self, z_dim, map_hidden_dim, map_output_dim):
        super().__init__()
        self.network = nn.Sequential(
            nn.Linear(z_dim, map_hidden_dim), nn.LeakyReLU(0.2, inplace=True),
            nn.Linear(map_hidden_dim, map_hidden_dim), nn.LeakyReLU(0.2, inplace=True),
            nn.Linear(map_hidden_dim, map_hidden_dim), nn.LeakyReLU(0.2, inplace=True),
            nn.Linear(map_hidden_dim, map_output_dim))
        self.network.apply(kaiming_leaky_init)
        with torch.no_grad():
            self.network[-1].weight *= 0.25

    def features(self, z):
        """w: the activation after the third LeakyReLU."""
        return self.network[:6](z)

    def head(self, w):
        out = self.network[6](w)
        half = out.shape[-1] // 2
        return out[..., :half], out[..., half:]

    def forward(self, z):
        return self.head(self.features(z))


# ----------------------------------------------------------------------------- fields

class TemplateSiren(nn.Module):
    """SPATIAL_SIREN_TEMPLATE_DEFERDIR: unconditioned density trunk, FiLM colour branch,
    direction concatenated in front of the last colour layer."""

    def __init__(self, z_dim=256, hidden_dim=256, trunk=5, color=4, map_hidden=256):
        super().__init__()
        self.hidden_dim = hidden_dim
        self.network = nn.ModuleList([SINLayer(3, hidden_dim)] + [SINLayer(hidden_dim, hidden_dim) for _ in range(trunk - 1)])
        self.final_layer = nn.Linear(hidden_dim, 1)
        self.color_network = nn.ModuleList(
            [FiLMLayer(hidden_dim, hidden_dim) for _ in range(color - 1)] + [FiLMLayer(hidden_dim + 3, hidden_dim)])
        self.color_layer_linear = nn.Sequential(nn.Linear(hidden_dim, 3))
        self.mapping_network = CustomMappingNetwork(z_dim, map_hidden, color * hidden_dim * 2)
        self.network.apply(frequency_init(30))
        self.final_layer.apply(frequency_init(30))
        self.color_network.apply(frequency_init(25))
        self.color_layer_linear.apply(frequency_init(25))
        self.network[0].apply(first_layer_sine_init)
        self.color_network[0].apply(first_layer_sine_init)

    def density(self, x):
        for layer in self.network:
            x = layer(x)
        return x, self.final_layer(x)

    def color(self, feature, ray_directions, frequencies, phase_shifts):
        frequencies = frequencies * 15 + 30
        x = feature
        last = len(self.color_network) - 1
        for i, layer in enumerate(self.color_network):
            s, e = i * self.hidden_dim, (i + 1) * self.hidden_dim
            if i == last:
                x = torch.cat([ray_directions, x], dim=-1)
            x = layer(x, frequencies[..., s:e], phase_shifts[..., s:e])
        return torch.sigmoid(self.color_layer_linear(x))


class DeformSiren(nn.Module):
    """SPATIAL_SIREN_DEFORM: 4 FiLM layers on raw xyz, head 256 → (Δx, raw Δσ)."""

    def __init__(self, z_dim=256, hidden_dim=256, layers=4, map_hidden=256):
        super().__init__()
        self.hidden_dim = hidden_dim
        self.network = nn.ModuleList([FiLMLayer(3, hidden_dim)] + [FiLMLayer(hidden_dim, hidden_dim) for _ in range(layers - 1)])
        self.final_layer = nn.Linear(hidden_dim, 4)
        self.mapping_network = CustomMappingNetwork(z_dim, map_hidden, layers * hidden_dim * 2)
        self.network.apply(frequency_init(25))
        self.final_layer.apply(frequency_init(25))
        self.network[0].apply(first_layer_sine_init)
        with torch.no_grad():
            self.final_layer.weight.zero_()

    def forward(self, x, frequencies, phase_shifts):
        frequencies = frequencies * 15 + 30
        for i, layer in enumerate(self.network):
            s, e = i * self.hidden_dim, (i + 1) * self.hidden_dim
            x = layer(x, frequencies[..., s:e], phase_shifts[..., s:e])
        return self.final_layer(x)


class ImplicitDeformation3D(nn.Module):
    def __init__(self, **kw):
        super().__init__()
        self.siren = DeformSiren(**kw)
        self.correct_scale = 100.0

    def forward(self, x, frequencies, phase_shifts):
        out = self.siren(x, frequencies, phase_shifts)
        return out[..., :3], out[..., 3:4] * self.correct_scale


class Generator(nn.Module):
    """Template field `siren` and deformation `deformnet`, as in the release."""

    def __init__(self, z_dim=256, hidden_dim=256, map_hidden=256, trunk=5, color=4, deform_layers=4,
                 correct_scale=100.0):
        super().__init__()
        self.siren = TemplateSiren(z_dim, hidden_dim, trunk=trunk, color=color, map_hidden=map_hidden)
        self.deformnet = ImplicitDeformation3D(z_dim=z_dim, hidden_dim=hidden_dim, layers=deform_layers,
                                               map_hidden=map_hidden)
        self.deformnet.correct_scale = correct_scale

    def field(self, x, dirs, shape, appearance):
        """x, dirs: (B, P, 3); shape / appearance: (raw frequencies, phases) → (rgb, σ, f_t, Δx, Δσ, σ_t)."""
        dx, dsigma = self.deformnet(x, *shape)
        feature, sigma_t = self.siren.density(x + dx)
        rgb = self.siren.color(feature, dirs, *appearance)
        return rgb, sigma_t + dsigma, feature, dx, dsigma, sigma_t


# ----------------------------------------------------------------------------- cameras

def normalize_vecs(v):
    return v / torch.norm(v, dim=-1, keepdim=True)


def camera_dirs(res, fov, dtype):
    """(res*res, 3) camera-space unit directions, row-major, pixel centres on ±1."""
    x, y = torch.meshgrid(torch.linspace(-1, 1, res, dtype=dtype), torch.linspace(1, -1, res, dtype=dtype), indexing="ij")
    x, y = x.T.flatten(), y.T.flatten()
    z = -torch.ones_like(x) / math.tan((2 * math.pi * fov / 360) / 2)
    return normalize_vecs(torch.stack([x, y, z], -1))


def camera_origin(pitch, yaw, r=1.0):
    out = torch.zeros(pitch.shape[0], 3, dtype=pitch.dtype)
    out[:, 0:1] = r * torch.sin(pitch) * torch.cos(yaw)
    out[:, 2:3] = r * torch.sin(pitch) * torch.sin(yaw)
    out[:, 1:2] = r * torch.cos(pitch)
    return out


def cam2world(pitch, yaw):
    origin = camera_origin(pitch, yaw)
    forward = normalize_vecs(-origin)
    up = torch.tensor([0, 1, 0], dtype=pitch.dtype).expand_as(forward)
    left = normalize_vecs(torch.cross(up, forward, dim=-1))
    up = normalize_vecs(torch.cross(forward, left, dim=-1))
    rot = torch.eye(4, dtype=pitch.dtype).unsqueeze(0).repeat(forward.shape[0], 1, 1)
    rot[:, :3, :3] = torch.stack((-left, up, -forward), dim=-1)
    trans = torch.eye(4, dtype=pitch.dtype).unsqueeze(0).repeat(forward.shape[0], 1, 1)
    trans[:, :3, 3] = origin
    return trans @ rot


def world_rays(pitch, yaw, res, fov):
    """origins, dirs: (B, R, 3)."""
    c2w = cam2world(pitch, yaw)
    d = camera_dirs(res, fov, pitch.dtype)
    dirs = torch.einsum("bij,rj->bri", c2w[:, :3, :3], d)
    origins = c2w[:, :3, 3].unsqueeze(1).expand_as(dirs)
    return origins, dirs


# ----------------------------------------------------------------------------- sampling

def stratified(b, r, n, ray_start, ray_end, jitter, dtype):
    z = torch.linspace(ray_start, ray_end, n, dtype=dtype).reshape(1, 1, n).repeat(b, r, 1)
    if jitter is not None:
        z = z + (jitter - 0.5) * ((ray_end - ray_start) / (n - 1))
    return z


def sample_pdf(bins, weights, u, eps=1e-5):
    n_rays, n_samples_ = weights.shape
    weights = weights + eps
    pdf = weights / torch.sum(weights, -1, keepdim=True)
    cdf = torch.cumsum(pdf, -1)
    cdf = torch.cat([torch.zeros_like(cdf[:, :1]), cdf], -1)
    u = u.contiguous()
    n_imp = u.shape[1]
    inds = torch.searchsorted(cdf, u)
    below = torch.clamp_min(inds - 1, 0)
    above = torch.clamp_max(inds, n_samples_)
    inds_sampled = torch.stack([below, above], -1).view(n_rays, 2 * n_imp)
    cdf_g = torch.gather(cdf, 1, inds_sampled).view(n_rays, n_imp, 2)
    bins_g = torch.gather(bins, 1, inds_sampled).view(n_rays, n_imp, 2)
    denom = cdf_g[..., 1] - cdf_g[..., 0]
    denom[denom < eps] = 1
    return bins_g[..., 0] + (u - cdf_g[..., 0]) / denom * (bins_g[..., 1] - bins_g[..., 0])


def importance(z, weights, u):
    """z, weights: (M, N) coarse; u: (M, N) → (M, N) fine depths."""
    weights = weights + 1e-5
    mids = 0.5 * (z[:, :-1] + z[:, 1:])
    return sample_pdf(mids, weights[:, 1:-1], u)


# ----------------------------------------------------------------------------- integration

def integrate(rgb, sigma, z, white_back=True, last_back=False, force_last_white=False, delta_final=1e10, widen_eps=1e-3):
    """rgb (..., S, 3) in (0,1), raw sigma (..., S, 1), sorted z (..., S, 1)."""
    if force_last_white:
        rgb = torch.cat([rgb[..., :-1, :], torch.ones_like(rgb[..., -1:, :])], -2)
    rgb = rgb * (1 + 2 * widen_eps) - widen_eps
    deltas = z[..., 1:, :] - z[..., :-1, :]
    deltas = torch.cat([deltas, delta_final * torch.ones_like(deltas[..., :1, :])], -2)
    alphas = 1 - torch.exp(-deltas * F.softplus(sigma))
    shifted = torch.cat([torch.ones_like(alphas[..., :1, :]), 1 - alphas + 1e-10], -2)
    weights = alphas * torch.cumprod(shifted, -2)[..., :-1, :]
    opacity = weights.sum(-2)
    if last_back:
        weights = torch.cat([weights[..., :-1, :], weights[..., -1:, :] + (1 - opacity).unsqueeze(-2)], -2)
    pixel = torch.sum(weights * rgb, -2)
    if white_back:
        pixel = pixel + 1 - opacity
    total = weights.sum(-2)
    depth = torch.where(total > 1e-10, torch.sum(weights * z, -2) / total.clamp_min(1e-10), z[..., -1, :])
    return pixel, depth, weights, opacity


# ----------------------------------------------------------------------------- renderer

def render(gen, shape, appearance, pitch, yaw, res, fov, ray_start, ray_end, n, jitter, imp_u,
           lock_view_dependence=False, return_samples=False, **integ):
    """Renders (B, 3, res, res) in [-1, 1]; jitter and imp_u are (B, R, n) uniforms. With
    return_samples, also the sorted depths z (B, R, 2n), expected depth (B, R, 1), ray
    origins and directions (B, R, 3), and the integration weights (B, R, 2n, 1)."""
    b = pitch.shape[0]
    r = res * res
    origins, dirs = world_rays(pitch, yaw, res, fov)
    if lock_view_dependence:
        dirs_in = torch.zeros_like(dirs)
        dirs_in[..., 2] = -1
    else:
        dirs_in = dirs
    z_c = stratified(b, r, n, ray_start, ray_end, jitter, pitch.dtype)

    def query(z):
        pts = origins.unsqueeze(2) + dirs.unsqueeze(2) * z.unsqueeze(-1)
        d = dirs_in.unsqueeze(2).expand(-1, -1, z.shape[2], -1)
        rgb, sigma, *_ = gen.field(pts.reshape(b, -1, 3), d.reshape(b, -1, 3), shape, appearance)
        return rgb.reshape(b, r, -1, 3), sigma.reshape(b, r, -1, 1)

    rgb_c, sigma_c = query(z_c)
    with torch.no_grad():
        _, _, w, _ = integrate(rgb_c, sigma_c, z_c.unsqueeze(-1), delta_final=integ.get("delta_final", 1e10))
        z_f = importance(z_c.reshape(b * r, n), w.reshape(b * r, n), imp_u.reshape(b * r, n)).reshape(b, r, n)
    rgb_f, sigma_f = query(z_f)
    z_all = torch.cat([z_f, z_c], -1)
    z_all, idx = torch.sort(z_all, -1)
    rgb = torch.gather(torch.cat([rgb_f, rgb_c], -2), 2, idx.unsqueeze(-1).expand(-1, -1, -1, 3))
    sigma = torch.gather(torch.cat([sigma_f, sigma_c], -2), 2, idx.unsqueeze(-1))
    pixel, depth, weights, opacity = integrate(rgb, sigma, z_all.unsqueeze(-1), **integ)
    img = pixel.reshape(b, res, res, 3).permute(0, 3, 1, 2) * 2 - 1
    out = (img, depth.reshape(b, 1, res, res), opacity.reshape(b, 1, res, res))
    if return_samples:
        out += (dict(z=z_all, depth=depth, origins=origins, dirs=dirs, weights=weights),)
    return out
