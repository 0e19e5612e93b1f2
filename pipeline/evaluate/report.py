"""The evaluation report: one Markdown page with, per evaluated size, the overall table, the refined
normals' ratios against the narrow-range and bilateral filters, and per-sequence tables."""

from __future__ import annotations

from pathlib import Path

from pipeline import cache
from pipeline.methods import NAMES

NAN = float("nan")

HEADER = ("| method | mean (deg) | median (deg) | < 5 deg | < 10 deg | < 20 deg | missed | IoU | PSNR (dB) | "
          "SSIM | flicker (deg) | temporal (deg) | ms/frame | mean on its mask (deg) |")


def method_row(name: str, r: dict) -> str:
    """One row of the overall table."""
    return (f"| {name} | {r['mean_deg']:.2f} | {r['median_deg']:.2f} | {100 * r['under_5']:.1f}% "
            f"| {100 * r['under_10']:.1f}% | {100 * r['under_20']:.1f}% | {100 * r['missed']:.2f}% | {r['iou']:.3f} "
            f"| {r['psnr']:.2f} | {r['ssim']:.3f} | {r['flicker_deg']:.2f} | {r.get('temporal_deg', NAN):.2f} "
            f"| {r['ms_per_frame']:.0f} "
            f"| {r['mask_mean_deg']:.2f} |")


def ratios(table: dict, method: str = "refined") -> dict[str, float]:
    """``method``'s mean and median error and flicker as multiples of the narrow-range and bilateral
    filters' (the figures issue 10's goals are stated in); empty when either is missing."""
    if method not in table or "nrf" not in table or "bilateral" not in table:
        return {}
    r = table[method]
    out = {}
    for base in ("nrf", "bilateral"):
        for k in ("mean_deg", "median_deg", "flicker_deg", "temporal_deg"):
            mine, theirs = r.get(k, NAN), table[base].get(k, NAN)
            out[f"{k}/{base}"] = mine / theirs if theirs else NAN
    return out


def write_report(folder: Path, by_size: dict[int, tuple[list[dict], dict]], methods, weights: str) -> None:
    """report.md: per size the overall table, the refined/narrow-range and refined/bilateral ratios,
    then the per-sequence tables; figures (of the first size) below the first table."""
    sizes = list(by_size)
    first_results = by_size[sizes[0]][0]
    lines = ["# Evaluation: normal maps against the anisotropic marching-cubes mesh", "",
             f"Held-out sequences: {len(first_results)} at each of {', '.join(f'{s} x {s}' for s in sizes)} px; "
             f"generator checkpoint `{weights}`. Errors are over every pixel where the mesh shows fluid, one pixel "
             "set for every method: a pixel the method misses scores 90 degrees (their share: missed), an extra "
             "one counts against its IoU; the last column is the older figure, over the pixels where both the "
             "method and the mesh show fluid. PSNR/SSIM compare the shaded image with the shaded mesh "
             "(tone-mapped, [0, 1]); flicker is the mean frame-to-frame change of the mean error (sequences of "
             "more than one frame); temporal is the per-pixel temporal error: the angle between a method's change "
             "of normal and the mesh's own change at each mesh pixel followed to the next evaluated frame with the "
             "exact particle motion (pipeline/evaluate/temporal.py). Overall figures weight each sequence by its "
             "pixels (means, shares) or take the median of the sequences' medians.", ""]
    summary = [r for r in (ratios(by_size[s][1]) for s in sizes) if r]
    if summary:
        lines += ["## Refined against the filters", "",
                  "| size | mean / narrow-range | median / narrow-range | mean / bilateral | median / bilateral | "
                  "flicker / bilateral | temporal / bilateral | temporal / narrow-range | IoU |",
                  "|---|---|---|---|---|---|---|---|---|"]
        for s in sizes:
            q, table = ratios(by_size[s][1]), by_size[s][1]
            if q:
                lines.append(f"| {s} | {q['mean_deg/nrf']:.3f} | {q['median_deg/nrf']:.3f} | "
                             f"{q['mean_deg/bilateral']:.3f} | {q['median_deg/bilateral']:.3f} | "
                             f"{q['flicker_deg/bilateral']:.3f} | {q['temporal_deg/bilateral']:.3f} | "
                             f"{q['temporal_deg/nrf']:.3f} | {table['refined']['iou']:.3f} |")
        lines.append("")
    if "metaball" in methods:
        lines += ["## Metaballs against their own ray-marched surface", "",
                  "The metaball network's normals and silhouette against the metaball surface its particles make "
                  "(ray-marched, what it was trained to predict), on every `metaball.target_stride`-th evaluated "
                  "frame; the tables below compare it with the mesh like every other method. The last column "
                  "scores the ray-marched surface itself against the mesh (the same frames and rule): what a "
                  "network that reproduced it exactly would score there.", "",
                  "| size | mean (deg) | median (deg) | IoU | against the mesh: mean (deg) | IoU | "
                  "the surface against the mesh: mean / median (deg) |",
                  "|---|---|---|---|---|---|---|"]
        for s in sizes:
            t = by_size[s][1]["metaball"]
            lines.append(f"| {s} | {t['own_mean_deg']:.2f} | {t['own_median_deg']:.2f} | {t['own_iou']:.3f} | "
                         f"{t['mean_deg']:.2f} | {t['iou']:.3f} | {t['surface_mean_deg']:.2f} / "
                         f"{t['surface_median_deg']:.2f} |")
        lines.append("")
    for i, s in enumerate(sizes):
        results, table = by_size[s]
        lines += [f"## {s} x {s}", "", HEADER, "|" + "---|" * 14]
        lines += [method_row(NAMES.get(m, m), table[m]) for m in methods]
        lines += [f"| mesh (reference) | 0 | 0 | | | | 0 | 1 | | | | 0 | {table['mesh']['ms_per_frame']:.0f} | 0 |",
                  ""]
        if i == 0:
            lines += ["![mean error per method](methods.png)", "", "![error over frames](frames.png)", "",
                      "![examples](examples.png)", ""]
        lines += [f"### Per sequence at {s} x {s}", ""]
        for res in results:
            lines += [f"#### {res['scene']} / {res['camera']} ({res['frames']} frames, particles "
                      f"{res.get('radius_px', 0):.1f} px)", "",
                      "| method | mean (deg) | median (deg) | < 10 deg | missed | IoU | PSNR | SSIM | flicker | "
                      "temporal |", "|---|---|---|---|---|---|---|---|---|---|"]
            for m in methods:
                r = res["methods"][m]
                lines.append(f"| {NAMES.get(m, m)} | {r['mean_deg']:.2f} | {r['median_deg']:.2f} | "
                             f"{100 * r['under_10']:.1f}% | {100 * r['missed']:.2f}% | {r['iou']:.3f} | "
                             f"{r['psnr']:.2f} | {r['ssim']:.3f} | "
                             f"{r['flicker_deg']:.2f} | {r.get('temporal_deg', NAN):.2f} |")
            lines.append("")
    with cache.atomic_path(folder / "report.md") as tmp:
        tmp.write_text("\n".join(lines))
