#!/usr/bin/env python3
"""Writes cross-check cases for the Rust test suite: the reference model's weights (through
the official-checkpoint converter), inputs, and the reference outputs and gradients.

    crosscheck.py generator --out DIR --dtype float32|float64 [--seed 0]

Writes DIR/model.safetensors (a gdrf checkpoint), DIR/case.safetensors (inputs and
expected outputs) and DIR/case.json (scalar settings).
"""
import argparse
import copy
import json
import os
import sys

import torch
import torch.nn.functional as F
from safetensors.torch import save_file

HERE = os.path.dirname(os.path.abspath(__file__))
sys.path.insert(0, HERE)
sys.path.insert(0, os.path.dirname(HERE))

import gdrf_ref as ref  # noqa: E402
import losses_ref as L  # noqa: E402
from names import release_to_gdrf  # noqa: E402
import convert_official_checkpoint as conv  # noqa: E402


def generator_case(out, dtype, seed):
    torch.manual_seed(seed)
    gen = ref.Generator()
    # Give the zero-initialised deformation head real weights so that Δx varies with x and
    # every parameter receives a gradient.
    with torch.no_grad():
        gen.deformnet.siren.final_layer.weight.uniform_(-0.02, 0.02)
    gen = gen.to(dtype)
    pth = os.path.join(out, "generator.pth")
    torch.save(gen.state_dict(), pth)
    conv.main([pth, os.path.join(out, "model.safetensors"), "--camera", "chair"])

    s = dict(fov=50.0, ray_start=0.6, ray_end=1.4, num_steps=12, resolutions=[12, 20], psi=0.7,
             ray_res=6, batch=2, points=64)
    t, e = {}, {}  # inputs, expected
    B, P = s["batch"], s["points"]
    rnd = lambda *shape: torch.rand(*shape, dtype=dtype)  # noqa: E731
    t["z_s"] = torch.randn(B, 256, dtype=dtype)
    t["z_a"] = torch.randn(B, 256, dtype=dtype)
    t["points"] = (rnd(B, P, 3) - 0.5) * 1.2
    t["dirs"] = ref.normalize_vecs(torch.randn(B, P, 3, dtype=dtype))

    M_s, M_a = gen.deformnet.siren.mapping_network, gen.siren.mapping_network
    with torch.no_grad():
        fs, ps = M_s(t["z_s"])
        fa, pa = M_a(t["z_a"])
        e["w_s"] = M_s.features(t["z_s"])
        e["shape_raw"] = torch.cat([fs, ps], -1)
        e["appearance_raw"] = torch.cat([fa, pa], -1)
        rgb, sigma, feat, dx, dsigma, sigma_t = gen.field(t["points"], t["dirs"], (fs, ps), (fa, pa))
        e.update(field_rgb=rgb, field_sigma=sigma, field_feature=feat, field_dx=dx, field_dsigma=dsigma,
                 field_sigma_t=sigma_t)
        # Truncation toward given means.
        t["shape_mean"] = torch.randn(1, fs.shape[1] * 2, dtype=dtype) * 0.1
        t["appearance_mean"] = torch.randn(1, fa.shape[1] * 2, dtype=dtype) * 0.1
        psi = s["psi"]
        e["shape_raw_trunc"] = t["shape_mean"] + psi * (e["shape_raw"] - t["shape_mean"])
        e["appearance_raw_trunc"] = t["appearance_mean"] + psi * (e["appearance_raw"] - t["appearance_mean"])

        # Rays for several poses, including yaw ±π and pitches near the poles.
        pitch = torch.tensor([[0.3], [1.07], [1.57], [2.8], [0.01], [3.13]], dtype=dtype)
        yaw = torch.tensor([[0.0], [-3.14159], [3.14159], [1.0], [-0.7], [2.2]], dtype=dtype)
        t["ray_pitch"], t["ray_yaw"] = pitch, yaw
        e["ray_origins"], e["ray_dirs"] = ref.world_rays(pitch, yaw, s["ray_res"], s["fov"])

        # Samplers.
        n = s["num_steps"]
        t["strat_jitter"] = rnd(B, 5, n)
        e["strat_z"] = ref.stratified(B, 5, n, s["ray_start"], s["ray_end"], t["strat_jitter"], dtype)
        e["strat_z_plain"] = ref.stratified(B, 5, n, s["ray_start"], s["ray_end"], None, dtype)
        M = 9
        t["imp_z"] = ref.stratified(M, 1, n, s["ray_start"], s["ray_end"], rnd(M, 1, n), dtype).reshape(M, n)
        w = rnd(M, n) ** 4
        w[0] = 0
        w[1] = 0
        w[1, 5] = 1
        t["imp_weights"] = w
        t["imp_u"] = rnd(M, n)
        e["imp_fine"] = ref.importance(t["imp_z"], t["imp_weights"], t["imp_u"])

        # Integration under each option.
        S = 16
        t["int_rgb"] = rnd(M, S, 3)
        t["int_sigma"] = torch.randn(M, S, 1, dtype=dtype) * 3
        t["int_sigma"][0] = -200.0  # an empty ray (softplus underflows)
        t["int_z"] = torch.sort(rnd(M, S, 1) * 0.8 + 0.6, dim=1).values
        for tag, opts in dict(default={}, lastback=dict(last_back=True, white_back=False),
                              forcewhite=dict(force_last_white=True), shortfinal=dict(delta_final=0.05)).items():
            pix, dep, wts, opa = ref.integrate(t["int_rgb"], t["int_sigma"], t["int_z"], **opts)
            e[f"int_{tag}_pixel"], e[f"int_{tag}_depth"] = pix, dep
            e[f"int_{tag}_weights"], e[f"int_{tag}_opacity"] = wts, opa

    # Full renders at two resolutions; gradients at the first.
    t["render_pitch"] = torch.tensor([[1.0], [1.25]], dtype=dtype)
    t["render_yaw"] = torch.tensor([[0.4], [-2.0]], dtype=dtype)
    common = dict(fov=s["fov"], ray_start=s["ray_start"], ray_end=s["ray_end"], n=n)
    for k, res in enumerate(s["resolutions"]):
        r = res * res
        t[f"render{res}_jitter"] = rnd(B, r, n)
        t[f"render{res}_imp"] = rnd(B, r, n)
        t[f"render{res}_probe"] = torch.randn(B, 3, res, res, dtype=dtype)
        args = (t["render_pitch"], t["render_yaw"], res, common["fov"], common["ray_start"], common["ray_end"], n,
                t[f"render{res}_jitter"], t[f"render{res}_imp"])
        gen.zero_grad()
        img, depth, opacity = ref.render(gen, M_s(t["z_s"]), M_a(t["z_a"]), *args)
        e[f"render{res}_rgb"], e[f"render{res}_depth"], e[f"render{res}_opacity"] = img.detach(), depth.detach(), opacity.detach()
        if k == 0:
            (img * t[f"render{res}_probe"]).sum().backward()
            for name, p in gen.named_parameters():
                e["grad." + release_to_gdrf(name)] = p.grad.detach().clone()
            # Features: w_s, γ_a, β_a as leaves.
            w_s = M_s.features(t["z_s"]).detach().requires_grad_(True)
            fa, pa = M_a(t["z_a"])
            gamma_a = (fa * 15 + 30).detach().requires_grad_(True)
            beta_a = pa.detach().requires_grad_(True)
            img2, _, _ = ref.render(gen, M_s.head(w_s), ((gamma_a - 30) / 15, beta_a), *args)
            g = torch.autograd.grad((img2 * t[f"render{res}_probe"]).sum(), [w_s, gamma_a, beta_a])
            e["grad_w_s"], e["grad_gamma_a"], e["grad_beta_a"] = g
            e["render_features_rgb"] = img2.detach()
            # The inversion's silhouette term on the first image: mean (O − S)², O the
            # object's share of each pixel (every weight but the far sample's), against a
            # random target; gradients w.r.t. w_s and the pose (pitch, yaw) as leaves.
            t["sil_target"] = rnd(1, 1, res, res)
            w_s1 = M_s.features(t["z_s"][:1]).detach().requires_grad_(True)
            pitch1 = t["render_pitch"][:1].clone().requires_grad_(True)
            yaw1 = t["render_yaw"][:1].clone().requires_grad_(True)
            fa1, pa1 = M_a(t["z_a"][:1])
            *_, smp = ref.render(gen, M_s.head(w_s1), (fa1.detach(), pa1.detach()), pitch1, yaw1, res, common["fov"],
                                 common["ray_start"], common["ray_end"], n, t[f"render{res}_jitter"][:1],
                                 t[f"render{res}_imp"][:1], return_samples=True)
            share = smp["weights"][..., :-1, :].sum(-2).reshape(1, 1, res, res)
            sil = ((share - t["sil_target"]) ** 2).mean()
            g = torch.autograd.grad(sil, [w_s1, pitch1, yaw1])
            e["sil_opacity"], e["sil_loss"] = share.detach(), sil.detach()
            e["grad_sil_w_s"], e["grad_sil_pitch"], e["grad_sil_yaw"] = g
        # Truncated render (ψ) with locked view dependence at the second resolution.
        if k == 1:
            with torch.no_grad():
                raw_s = t["shape_mean"] + s["psi"] * (torch.cat(M_s(t["z_s"]), -1) - t["shape_mean"])
                raw_a = t["appearance_mean"] + s["psi"] * (torch.cat(M_a(t["z_a"]), -1) - t["appearance_mean"])
                h_s, h_a = raw_s.shape[1] // 2, raw_a.shape[1] // 2
                img3, _, _ = ref.render(gen, (raw_s[:, :h_s], raw_s[:, h_s:]), (raw_a[:, :h_a], raw_a[:, h_a:]),
                                        *args, lock_view_dependence=True, force_last_white=True)
            e[f"render{res}_trunc_locked_rgb"] = img3

    # Seeds name the same codes as torch.manual_seed(s); torch.randn(1, 256).
    codes = []
    for seed in (0, 1, 42):
        torch.manual_seed(seed)
        codes.append(torch.randn(1, 256))
    e["seed_codes"] = torch.cat(codes)

    tensors = {k: v.detach().contiguous() for k, v in t.items()}
    tensors.update({"expected." + k: v.detach().contiguous() for k, v in e.items()})
    save_file(tensors, os.path.join(out, "case.safetensors"))
    with open(os.path.join(out, "case.json"), "w") as f:
        json.dump(s, f)


def losses_case(out, dtype, seed):
    """Discriminator outputs at several sizes and α, every loss term, and the gradients of
    the generator's and discriminator's totals w.r.t. all parameters and the real images."""
    torch.manual_seed(seed)
    gen = ref.Generator()
    with torch.no_grad():
        gen.deformnet.siren.final_layer.weight.uniform_(-0.02, 0.02)
    gen = gen.to(dtype)
    disc = L.Discriminator().to(dtype)
    pth = os.path.join(out, "generator.pth")
    torch.save(gen.state_dict(), pth)
    conv.main([pth, os.path.join(out, "model.safetensors"), "--camera", "chair"])
    save_file({L.disc_name_to_gdrf(k): v.contiguous() for k, v in disc.state_dict().items()},
              os.path.join(out, "disc.safetensors"))

    B, res, n, regions = 2, 16, 8, 2
    s = dict(fov=50.0, ray_start=0.6, ray_end=1.4, num_steps=n, resolution=res, regions=regions, batch=B,
             step=300000, topk_floor=0.3, alpha=0.7, disc_sizes=[32, 64, 128], disc_alphas=[1.0, 0.5])
    t, e = {}, {}
    rnd = lambda *shape: torch.rand(*shape, dtype=dtype)  # noqa: E731
    for size in s["disc_sizes"]:
        t[f"disc{size}_img"] = rnd(B, 3, size, size) * 2 - 1
        for a in s["disc_alphas"]:
            with torch.no_grad():
                lo, la, po = disc(t[f"disc{size}_img"], a)
            tag = f"disc{size}_a{int(a * 10)}"
            e[f"{tag}_logit"], e[f"{tag}_latent"], e[f"{tag}_pose"] = lo, la, po

    M_s, M_a = gen.deformnet.siren.mapping_network, gen.siren.mapping_network
    r = res * res
    t["z"] = torch.randn(B, 256, dtype=dtype)
    t["pitch"] = torch.tensor([[0.95], [1.2]], dtype=dtype)
    t["yaw"] = torch.tensor([[3.0], [-0.5]], dtype=dtype)
    t["g_jitter"], t["g_imp"] = rnd(B, r, n), rnd(B, r, n)
    n_reg = L.round_half_up(0.05 * r)
    t["reg_rays"] = torch.randint(r, (B, n_reg))
    args = lambda j, i: (t["pitch"], t["yaw"], res, s["fov"], s["ray_start"], s["ray_end"], n, j, i)  # noqa: E731

    # Generator loss (release regularisers) and its gradients.
    shape, app = M_s(t["z"]), M_a(t["z"])
    img, _, _, smp = ref.render(gen, shape, app, *args(t["g_jitter"], t["g_imp"]), return_samples=True)
    logit, _, pose = disc(img, s["alpha"])
    k = L.topk_count(s["step"], B, floor=s["topk_floor"])
    assert k == 1
    terms = dict(g_adv=L.g_adv(logit, k), g_pose=L.pose_loss(pose, torch.cat([t["pitch"], t["yaw"]], 1)))
    near, rest = L.select_release(smp, t["reg_rays"])
    reg = L.regularisers(gen, shape, near, rest)
    terms.update({"reg_" + k_: v for k_, v in reg.items()})
    total = terms["g_adv"] + 15 * terms["g_pose"] + sum(L.REG_WEIGHTS[k_] * v for k_, v in reg.items())
    gen.zero_grad()
    disc.zero_grad()
    total.backward()
    e["g_total"] = total
    for k_, v in terms.items():
        e["g." + k_] = v
    for name, p in gen.named_parameters():
        e["g_grad.gen." + release_to_gdrf(name)] = p.grad.clone()
    for name, p in disc.named_parameters():
        e["g_grad.disc." + L.disc_name_to_gdrf(name)] = p.grad.clone() if p.grad is not None else torch.zeros_like(p)

    # The paper's variant of the regularisers on the same render.
    img, _, _, smp = ref.render(gen, M_s(t["z"]), M_a(t["z"]), *args(t["g_jitter"], t["g_imp"]), return_samples=True)
    near, _ = L.select_paper(smp)
    reg = L.regularisers(gen, M_s(t["z"]), near, None, variant="paper")
    gen.zero_grad()
    psum = sum(L.REG_WEIGHTS[k_] * v for k_, v in reg.items())
    psum.backward()
    for k_, v in reg.items():
        e["paper." + k_] = v
    for name, p in gen.named_parameters():
        e["paper_grad." + release_to_gdrf(name)] = p.grad.clone() if p.grad is not None else torch.zeros_like(p)

    # Discriminator loss with R1 and its gradients (parameters and real images).
    t["d_jitter"], t["d_imp"] = rnd(B, r, n), rnd(B, r, n)
    t["real"] = rnd(B, 3, res, res) * 2 - 1
    t["real_pose"] = torch.tensor([[1.0, -3.1], [1.1, 2.0]], dtype=dtype)
    with torch.no_grad():
        fake, _, _ = ref.render(gen, M_s(t["z"]), M_a(t["z"]), *args(t["d_jitter"], t["d_imp"]))
    real = t["real"].clone().requires_grad_(True)
    lr, _, pr = disc(real, s["alpha"])
    lf, _, pf = disc(fake, s["alpha"])
    terms = dict(d_real=F.softplus(-lr).mean(), d_fake=F.softplus(lf).mean(), d_r1=L.r1(lr, real),
                 d_pose_fake=L.pose_loss(pf, torch.cat([t["pitch"], t["yaw"]], 1)),
                 d_pose_real=L.pose_loss(pr, t["real_pose"]))
    total = terms["d_real"] + terms["d_fake"] + terms["d_r1"] + 15 * (terms["d_pose_fake"] + terms["d_pose_real"])
    disc.zero_grad()
    g_real = torch.autograd.grad(total, [real] + list(disc.parameters()), allow_unused=True)
    e["d_total"] = total
    for k_, v in terms.items():
        e["d." + k_] = v
    e["d_grad_real"] = g_real[0]
    for (name, p), g in zip(disc.named_parameters(), g_real[1:]):
        e["d_grad.disc." + L.disc_name_to_gdrf(name)] = g if g is not None else torch.zeros_like(p)
    e["d_fake_img"] = fake
    # The same gradients in float64 from the same inputs and weights: the exact value a
    # float32 result is judged against. (On some CPUs PyTorch's own float32 gradients of
    # this loss are 1e-3 off it, e.g. 8e-4 at layers.5.conv2.weight on an AVX2-only CPU,
    # while a recomputation in a fresh process lands within 1e-6.)
    disc64 = copy.deepcopy(disc).double()
    real64 = t["real"].double().requires_grad_(True)
    lr, _, pr = disc64(real64, s["alpha"])
    lf, _, pf = disc64(fake.double(), s["alpha"])
    pose64 = torch.cat([t["pitch"], t["yaw"]], 1).double()
    total64 = (F.softplus(-lr).mean() + F.softplus(lf).mean() + L.r1(lr, real64)
               + 15 * (L.pose_loss(pf, pose64) + L.pose_loss(pr, t["real_pose"].double())))
    g64 = torch.autograd.grad(total64, list(disc64.parameters()), allow_unused=True)
    for (name, p), g in zip(disc64.named_parameters(), g64):
        e["d_grad64.disc." + L.disc_name_to_gdrf(name)] = g if g is not None else torch.zeros_like(p)

    tensors = {k_: v.detach().contiguous() for k_, v in t.items()}
    tensors.update({"expected." + k_: v.detach().contiguous() for k_, v in e.items()})
    save_file(tensors, os.path.join(out, "case.safetensors"))
    with open(os.path.join(out, "case.json"), "w") as f:
        json.dump(s, f)


def main():
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("case", choices=["generator", "losses"])
    ap.add_argument("--out", required=True)
    ap.add_argument("--dtype", choices=["float32", "float64"], default="float32")
    ap.add_argument("--seed", type=int, default=0)
    a = ap.parse_args()
    os.makedirs(a.out, exist_ok=True)
    torch.set_num_threads(max(1, os.cpu_count() or 1))
    dtype = dict(float32=torch.float32, float64=torch.float64)[a.dtype]
    dict(generator=generator_case, losses=losses_case)[a.case](a.out, dtype, a.seed)


if __name__ == "__main__":
    main()
