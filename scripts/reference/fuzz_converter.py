#!/usr/bin/env python3
"""Fuzz scripts/convert_official_checkpoint.py with mutated release-shaped files.

    fuzz_converter.py --dir DIR [--cases N] [--seed S]

Writes release-shaped generator.pth and ema.pth into DIR (make_release_checkpoint.py),
then runs the converter's main() in this process on N mutated copies (bit flips,
interesting bytes, insertions, deletions, truncations, copied chunks; each case mutates
the generator or the EMA file). Each run must either convert or exit with status 1 and a
message naming the mutated file; any other exception, exit status or a temporary file left
beside the output is a finding. Memory is capped (RLIMIT_AS, 8 GiB), so a file that makes
torch.load allocate what its bytes do not justify shows as a finding too. Prints a JSON
summary; exits 1 when anything was found.
"""
import argparse
import contextlib
import io
import json
import os
import random
import resource
import subprocess
import sys

HERE = os.path.dirname(os.path.abspath(__file__))
sys.path.insert(0, os.path.dirname(HERE))
import convert_official_checkpoint as conv  # noqa: E402

INTERESTING = [0, 0xFF, 0x7F, 0x80]
WIDE = [2**64 - 1, 2**32 - 1, 2**40, 0, 2**63 - 1]


def mutate(data, rng):
    b = bytearray(data)
    for _ in range(rng.randint(1, 5)):
        kind = rng.randrange(6)
        pos = rng.randrange(max(len(b), 1))
        if kind == 0 and b:
            b[pos] ^= 1 << rng.randrange(8)
        elif kind == 1 and b:
            b[pos] = rng.choice(INTERESTING)
        elif kind == 2:
            b[pos:pos] = rng.randbytes(rng.randint(1, 8))
        elif kind == 3:
            del b[pos:pos + rng.randint(1, 16)]
        elif kind == 4:
            del b[pos:]
        elif b:
            n = rng.choice(WIDE).to_bytes(8, "little")
            end = min(pos + 8, len(b))
            b[pos:end] = n[:end - pos]
    return bytes(b)


def run(argv):
    """main(argv) → (exit status, stderr)."""
    err = io.StringIO()
    with contextlib.redirect_stderr(err), contextlib.redirect_stdout(io.StringIO()):
        try:
            conv.main(argv)
            status = 0
        except SystemExit as e:
            status = e.code if isinstance(e.code, int) else 1
    return status, err.getvalue()


def main():
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--dir", required=True)
    ap.add_argument("--cases", type=int, default=60)
    ap.add_argument("--seed", type=int, default=20221012)
    a = ap.parse_args()
    subprocess.run([sys.executable, os.path.join(HERE, "make_release_checkpoint.py"), "--out", a.dir], check=True)
    soft, hard = resource.getrlimit(resource.RLIMIT_AS)
    cap = 8 << 30
    resource.setrlimit(resource.RLIMIT_AS, (cap if hard == resource.RLIM_INFINITY else min(cap, hard), hard))
    seeds = {n: open(os.path.join(a.dir, n), "rb").read() for n in ("generator.pth", "ema.pth")}
    out = os.path.join(a.dir, "out")
    os.makedirs(out, exist_ok=True)
    rng = random.Random(a.seed)
    counts = {"cases": a.cases, "converted": 0, "refused_naming_the_file": 0, "findings": []}
    for case in range(a.cases):
        target = rng.choice(sorted(seeds))
        files = {}
        for name, data in seeds.items():
            path = os.path.join(a.dir, f"case-{name}")
            with open(path, "wb") as f:
                f.write(mutate(data, rng) if name == target else data)
            files[name] = path
        dest = os.path.join(out, "chair.safetensors")
        try:
            status, err = run([files["generator.pth"], dest, "--ema", files["ema.pth"]])
        except Exception as e:  # noqa: BLE001 - every escaping exception is a finding
            counts["findings"].append(f"case {case} ({target}): {type(e).__name__}: {e}")
            continue
        left = [n for n in os.listdir(out) if n.startswith(".convert-")]
        if left:
            counts["findings"].append(f"case {case} ({target}): temporary files left: {left}")
        if status == 0:
            counts["converted"] += 1
        elif status == 1 and f"case-{target}" in err:
            counts["refused_naming_the_file"] += 1
        else:
            counts["findings"].append(f"case {case} ({target}): exit {status}: {err.strip()[-300:]}")
    print(json.dumps(counts, indent=2))
    sys.exit(1 if counts["findings"] else 0)


if __name__ == "__main__":
    main()
