#!/usr/bin/env python3
"""Time against error of `gdrf-edit bench`: one panel per scene and image size, each
configuration a point (ms per image, PSNR against the dense reference), the Pareto front
drawn through the points no other point beats on both; the PyTorch reference's time as a
vertical line.  plot_render_bench.py render.json out.png"""
import json
import sys

import matplotlib

matplotlib.use("Agg")
import matplotlib.pyplot as plt  # noqa: E402


def pareto(points):
    """Points (time, psnr) not dominated by a faster-and-more-accurate one, by time."""
    front, best = [], float("-inf")
    for t, p, name in sorted(points):
        if p > best:
            front.append((t, p, name))
            best = p
    return front


def main():
    src, out = sys.argv[1], sys.argv[2]
    with open(src) as f:
        data = json.load(f)
    rows = data["results"]
    panels = sorted({(r["scene"], r["resolution"]) for r in rows}, key=lambda k: (k[0] != "model", k[1]))
    cols = len({k[1] for k in panels})
    nrows = (len(panels) + cols - 1) // cols
    fig, axes = plt.subplots(nrows, cols, figsize=(5.2 * cols + 2.6, 4.0 * nrows), dpi=110, squeeze=False)
    # Families in the benchmark's order (the configuration's name before " N=").
    families = list(dict.fromkeys(r["config"].split(" N=")[0] for r in rows))
    # Filled markers only (thin ones vanish under the others), each family its own colour.
    shapes = "osv<D^>Ph*H8pdX"
    markers = {fam: shapes[i % len(shapes)] for i, fam in enumerate(families)}
    colours = {fam: plt.cm.tab20(i % 20) for i, fam in enumerate(families)}
    for ax, (scene, res) in zip(axes.flat, panels):
        sel = [r for r in rows if r["scene"] == scene and r["resolution"] == res]
        pts = []
        for fam in families:
            fr = [r for r in sel if r["config"].split(" N=")[0] == fam]
            if not fr:
                continue
            ax.scatter([r["ms_per_image"] for r in fr], [r["psnr_db"] for r in fr], marker=markers[fam],
                       color=colours[fam], label=fam, s=30)
            for r in fr:
                ax.annotate(f"N={r['steps']}", (r["ms_per_image"], r["psnr_db"]), fontsize=6, xytext=(3, 2),
                            textcoords="offset points")
                pts.append((r["ms_per_image"], r["psnr_db"], r["config"]))
        front = pareto(pts)
        ax.plot([p[0] for p in front], [p[1] for p in front], "k--", lw=0.8, label="Pareto front")
        for p in data.get("pytorch", []):
            if scene == "model" and p["resolution"] == res:
                ax.axvline(p["ms_per_image"], color="grey", lw=1, ls=":", label=f"PyTorch {p['config']}")
        ax.axhline(40, color="red", lw=0.6, ls=":")
        ax.set_xscale("log")
        ax.set_xlabel("ms per image (median)")
        ax.set_ylabel("PSNR vs dense reference (dB)")
        ax.set_title(f"{scene}, {res}×{res}", fontsize=9)
    for ax in list(axes.flat)[len(panels):]:
        ax.axis("off")
    # One legend beside the panels (inside them it hid the points), each label once.
    legend = {}
    for ax in axes.flat:
        for h, label in zip(*ax.get_legend_handles_labels()):
            legend.setdefault(label, h)
    fig.legend(legend.values(), legend.keys(), loc="center right", fontsize=7)
    fig.suptitle(f"{data.get('title', 'renderer')} — {data.get('device', '')}, {data.get('threads', '?')} threads", fontsize=9)
    fig.tight_layout(rect=(0, 0, 1 - 2.6 / (5.2 * cols + 2.6), 1))
    fig.savefig(out)


if __name__ == "__main__":
    main()
