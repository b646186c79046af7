#!/usr/bin/env bash
# Runs the whole test suite (Rust unit and integration tests, including the cross-checks
# against the PyTorch reference), setting the project up first when needed.
set -euo pipefail
root="$(cd "$(dirname "${BASH_SOURCE[0]}")/.." && pwd)"
cd "$root"
scripts/setup.sh
cargo test --workspace "$@"
