#!/usr/bin/env python3
"""Synthesises files shaped like the authors' release for converter tests:
DIR/generator.pth (a generator state dict), DIR/ema.pth (a torch_ema state whose shadow
list follows the release's parameter order), DIR/ema_short.pth (one shadow tensor short),
and DIR/expected_ema.safetensors (the shadow tensors under gdrf names).
"""
import argparse
import os
import sys

import torch
from safetensors.torch import save_file

sys.path.insert(0, os.path.dirname(os.path.abspath(__file__)))
import gdrf_ref as ref  # noqa: E402
from names import release_parameter_order, release_to_gdrf  # noqa: E402


def main():
    ap = argparse.ArgumentParser(description=__doc__)
    ap.add_argument("--out", required=True)
    a = ap.parse_args()
    os.makedirs(a.out, exist_ok=True)
    torch.manual_seed(1)
    gen = ref.Generator()
    names = [n for n, _ in gen.named_parameters()]
    if names != release_parameter_order():
        sys.exit(f"reference parameter order differs from the release's: {names}")
    state = gen.state_dict()
    torch.save(state, os.path.join(a.out, "generator.pth"))
    shadow = [p.detach() * 0.5 + 0.01 for p in gen.parameters()]
    ema = {"decay": 0.999, "num_updates": 10, "shadow_params": shadow, "collected_params": None}
    torch.save(ema, os.path.join(a.out, "ema.pth"))
    torch.save(dict(ema, shadow_params=shadow[:-1]), os.path.join(a.out, "ema_short.pth"))
    save_file({release_to_gdrf(n): t.contiguous() for n, t in zip(names, shadow)},
              os.path.join(a.out, "expected_ema.safetensors"))


if __name__ == "__main__":
    main()
