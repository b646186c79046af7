#!/usr/bin/env python3
"""Convert the authors' released GDRF generator (CHAIR_128, CAR_128, CARLA_128 …) into a
gdrf checkpoint (safetensors with a JSON header).

    scripts/convert_official_checkpoint.py generator.pth out.safetensors \
        [--ema ema.pth] [--camera chair|car|carla]

`generator.pth` may be a state dict, a dict holding one under 'state_dict' or
'generator', or a pickled generator module (then the release's code must be importable,
and --trust-pickle given: unpickling a module runs code from the file, so only files of
a source you trust should be opened that way; plain state dicts never need it).
`--ema` replaces the parameters by the EMA shadow (torch_ema state: 'shadow_params' in the
release's parameter order), as the authors' render and FID scripts do.
"""
import argparse
import json
import os
import pickle
import sys
import tempfile

sys.path.insert(0, os.path.join(os.path.dirname(os.path.abspath(__file__)), "reference"))
import torch  # noqa: E402
from safetensors.torch import save_file  # noqa: E402

from names import release_parameter_order, release_to_gdrf  # noqa: E402

CAMERAS = {
    "chair": dict(fov_deg=50.0, ray_start=0.6, ray_end=1.4, distribution="uniform", h_mean=0.0,
                  h_std=3.141592653589793, v_mean=1.070796, v_std=0.2618, lock_view_dependence=False),
    "car": dict(fov_deg=30.0, ray_start=0.75, ray_end=1.25, distribution="uniform", h_mean=0.0,
                h_std=3.141592653589793, v_mean=1.2217, v_std=0.2618, lock_view_dependence=False),
    "carla": dict(fov_deg=30.0, ray_start=0.7, ray_end=1.3, distribution="spherical_uniform",
                  h_mean=1.5707963267948966, h_std=3.141592653589793, v_mean=0.7418, v_std=0.7418,
                  lock_view_dependence=True),
}


def fail(msg):
    print(f"convert_official_checkpoint: error: {msg}", file=sys.stderr)
    sys.exit(1)


def load(path, trust_pickle):
    """torch.load, restricted to tensors and plain containers unless `trust_pickle`."""
    try:
        return torch.load(path, map_location="cpu", weights_only=not trust_pickle)
    except pickle.UnpicklingError as e:
        if not trust_pickle and "Unsupported global" in str(e):
            fail(f"{path}: holds pickled Python objects besides tensors (a whole module, as the release "
                 "saves); unpickling them runs code from the file: pass --trust-pickle if you trust its source")
        reason = str(e.__context__) if "Weights only load failed" in str(e) and e.__context__ else str(e)
        fail(f"{path}: cannot be read by torch.load ({reason})")
    except Exception as e:  # noqa: BLE001 - report any reading failure by file
        fail(f"{path}: cannot be read by torch.load ({type(e).__name__}: {e})")


def load_state_dict(path, trust_pickle=False):
    obj = load(path, trust_pickle)
    if isinstance(obj, torch.nn.Module):
        obj = obj.state_dict()
    if isinstance(obj, dict):
        for key in ("state_dict", "generator", "model"):
            if key in obj and isinstance(obj[key], dict):
                obj = obj[key]
                break
    if not isinstance(obj, dict) or not all(isinstance(v, torch.Tensor) for v in obj.values()):
        fail(f"{path}: expected a generator state dict (name → tensor)")
    return {k.removeprefix("module."): v for k, v in obj.items()}


def apply_ema(state, path, trust_pickle=False):
    ema = load(path, trust_pickle)
    if not isinstance(ema, dict):
        ema = getattr(ema, "state_dict", lambda: None)()
    shadow = ema.get("shadow_params") if isinstance(ema, dict) else None
    if shadow is None:
        fail(f"{path}: no 'shadow_params' (expected a torch_ema ExponentialMovingAverage state)")
    order = release_parameter_order()
    if len(shadow) != len(order):
        fail(f"{path}: {len(shadow)} shadow parameters, the release generator has {len(order)}")
    for name, t in zip(order, shadow):
        if name not in state or tuple(state[name].shape) != tuple(t.shape):
            fail(f"{path}: shadow parameter for '{name}' has shape {tuple(t.shape)}, "
                 f"the generator's is {tuple(state[name].shape) if name in state else 'missing'}")
        state[name] = t
    return state


def infer_config(state):
    def shape(name):
        if name not in state:
            fail(f"missing tensor '{name}' (not a GDRF generator?)")
        return tuple(state[name].shape)

    hidden, _ = shape("siren.network.0.layer.weight")
    map_hidden, latent = shape("siren.mapping_network.network.0.weight")
    trunk = len({k for k in state if k.startswith("siren.network.") and k.endswith(".layer.weight")})
    color = len({k for k in state if k.startswith("siren.color_network.") and k.endswith(".layer.weight")})
    deform = len({k for k in state if k.startswith("deformnet.siren.network.") and k.endswith(".layer.weight")})
    return dict(latent_dim=latent, hidden_dim=hidden, mapping_hidden_dim=map_hidden, trunk_layers=trunk,
                color_layers=color, deform_layers=deform, correct_scale=100.0, deform_scale=1.0)


def convert(state, camera=None, info=None):
    """Release state dict → (gdrf tensors, gdrf header dict)."""
    tensors = {}
    for name, t in state.items():
        new = release_to_gdrf(name)
        if new is None:
            continue  # unused buffers (e.g. the generator's blur kernel)
        tensors[new] = t.detach().contiguous()
    header = dict(format_version=1, model="generator", generator=infer_config(state),
                  camera=CAMERAS[camera] if camera else None, info=info or {})
    return tensors, header


def save_checkpoint(tensors, header, out):
    out_dir = os.path.dirname(os.path.abspath(out))
    fd, tmp = tempfile.mkstemp(prefix=".convert-", dir=out_dir)
    os.close(fd)
    try:
        save_file(tensors, tmp, metadata={"gdrf": json.dumps(header)})
        umask = os.umask(0)
        os.umask(umask)
        os.chmod(tmp, 0o666 & ~umask)
        os.replace(tmp, out)
    finally:
        if os.path.exists(tmp):
            os.remove(tmp)


def main(argv=None):
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("generator", help="the release's generator.pth")
    ap.add_argument("out", help="the gdrf checkpoint to write (.safetensors)")
    ap.add_argument("--ema", help="the release's ema.pth (EMA 0.999 shadow) to use instead of the raw weights")
    ap.add_argument("--camera", choices=sorted(CAMERAS), help="record the dataset's camera in the header")
    ap.add_argument("--trust-pickle", action="store_true",
                    help="also open files that hold pickled modules (runs code from them; trusted sources only)")
    a = ap.parse_args(argv)
    state = load_state_dict(a.generator, a.trust_pickle)
    if a.ema:
        state = apply_ema(state, a.ema, a.trust_pickle)
    tensors, header = convert(state, a.camera, {"converted_from": os.path.basename(a.generator),
                                                "ema": os.path.basename(a.ema) if a.ema else "none"})
    save_checkpoint(tensors, header, a.out)
    n = sum(t.numel() for t in tensors.values())
    print(f"wrote {a.out}: {len(tensors)} tensors, {n} parameters")


if __name__ == "__main__":
    main()
