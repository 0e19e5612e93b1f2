"""The evaluation report: one Markdown page with the overall table, per-sequence tables and figures."""

from __future__ import annotations

from pathlib import Path

from pipeline import cache
from pipeline.methods import NAMES


def write_report(folder: Path, results: list[dict], table: dict, methods, weights: str) -> None:
    """report.md with the overall table, per-sequence tables and figures."""
    lines = ["# Evaluation: normal maps against the anisotropic marching-cubes mesh", "",
             f"Held-out sequences: {len(results)}; generator checkpoint `{weights}`. Errors are over pixels where "
             "both the method and the mesh show fluid; PSNR/SSIM compare the shaded image with the shaded mesh "
             "(tone-mapped, [0, 1]); flicker is the mean frame-to-frame change of the mean error.", "",
             "| method | mean (deg) | median (deg) | < 5 deg | < 10 deg | < 20 deg | IoU | PSNR (dB) | SSIM | "
             "flicker (deg) | ms/frame |", "|" + "---|" * 11]
    for m in methods:
        r = table[m]
        lines.append(f"| {NAMES.get(m, m)} | {r['mean_deg']:.2f} | {r['median_deg']:.2f} | {100 * r['under_5']:.1f}% "
                     f"| {100 * r['under_10']:.1f}% | {100 * r['under_20']:.1f}% | {r['iou']:.3f} | {r['psnr']:.2f} "
                     f"| {r['ssim']:.3f} | {r['flicker_deg']:.2f} | {r['ms_per_frame']:.0f} |")
    lines += [f"| mesh (reference) | 0 | 0 | | | | 1 | | | | {table['mesh']['ms_per_frame']:.0f} |", "",
              "![mean error per method](methods.png)", "", "![error over frames](frames.png)", "",
              "![examples](examples.png)", "", "## Per sequence", ""]
    for res in results:
        lines += [f"### {res['scene']} / {res['camera']} ({res['frames']} frames)", "",
                  "| method | mean (deg) | < 10 deg | IoU | PSNR | SSIM |", "|---|---|---|---|---|---|"]
        for m in methods:
            r = res["methods"][m]
            lines.append(f"| {NAMES.get(m, m)} | {r['mean_deg']:.2f} | {100 * r['under_10']:.1f}% | {r['iou']:.3f} "
                         f"| {r['psnr']:.2f} | {r['ssim']:.3f} |")
        lines.append("")
    with cache.atomic_path(folder / "report.md") as tmp:
        tmp.write_text("\n".join(lines))
