#!/usr/bin/env python3
"""Bar chart of a benchmark JSON written by gdrf-bench: median seconds per phase for each
implementation.  plot_bench.py bench.json out.png"""
import json
import sys
import textwrap

import matplotlib

matplotlib.use("Agg")
import matplotlib.pyplot as plt  # noqa: E402


def main():
    src, out = sys.argv[1], sys.argv[2]
    with open(src) as f:
        data = json.load(f)
    runs = data["runs"]
    phases = data.get("phases") or list(runs[0]["median_s"].keys())
    fig, ax = plt.subplots(figsize=(7, 3.6), dpi=110)
    width = 0.8 / len(runs)
    for i, run in enumerate(runs):
        xs = [p + i * width for p in range(len(phases))]
        ys = [run["median_s"][p] for p in phases]
        bars = ax.bar(xs, ys, width, label=run["implementation"])
        ax.bar_label(bars, fmt="%.3g", fontsize=7)
    ax.set_xticks([p + width * (len(runs) - 1) / 2 for p in range(len(phases))], phases)
    ax.set_ylabel("median seconds")
    ax.set_title("\n".join(textwrap.wrap(data.get("title", "benchmark"), 90)), fontsize=9)
    ax.legend(fontsize=8)
    fig.tight_layout()
    fig.savefig(out)


if __name__ == "__main__":
    main()
