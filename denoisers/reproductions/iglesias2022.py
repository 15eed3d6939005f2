"""Iglesias-Guitian et al. 2022, wRLS for volumetric path tracing (../shared/papers/iglesias-guitian2022-wrls-
volumetric.txt): the paper's comparison on the volumetric clips (config section ``volumes``: a table per
scenario, per-frame PSNR curves like Figs. 10-12, image grids) with claims C4.1-C4.3 decided on those clips; the
same comparison on the evaluated surface scenes, labelled as such (C4.1s, C4.2s, C4.3s); and C4.4 (speed). FLIP
and SSIM stand in for LPIPS (no network weights can be downloaded here).

On the volumes, SVGF is ``svgf_volume`` (no normals; the clips' reprojection, as the paper did) and the RAE is a
volume row of ``rae_color``, trained colour-only on volumetric clips (the paper's protocol); without one, the
RAE part of C4.3 is not run.
"""
from __future__ import annotations

from collections.abc import Callable
from pathlib import Path
from typing import TYPE_CHECKING, Any

from denoisers.report.claims import (Claim, RowNeed, compare_rows, compare_speed, row_at, seed_differences, seeds_of,
                                     spp_available, training_spp)
from denoisers.report.verdicts import Decision, Fact, Part, not_run
from denoisers.report.seeds import seed_mean
from denoisers.report.stats import LABELS, fmt_ci, frame_to_markdown, mean_ci
from denoisers.reproductions.base import Reproduction

if TYPE_CHECKING:
    import pandas as pd

    from denoisers.report.collect import Results
    from denoisers.report.seeds import SeedAveraged

PAPER = "Iglesias-Guitian 2022"
PAPER_SPP = 2
#: Registry methods of an RAE row on the volumetric clips, preferred first.
RAE_VOLUME_METHODS = ("rae_color", "rae")
SURFACES = "on our evaluated surface scenes, not volumes (the paper's setting; see C4.1 / C4.3 for the volumes)"
#: The paper reconstructs its volumetric renders with a separable Gaussian pixel filter (§6); ours are box-filtered
#: (one-pixel box: the per-sample layers need it), so a volume verdict holds for this pipeline, not the paper's.
PIXEL_FILTER = ("box pixel filter on inputs and references (the paper's: separable Gaussian, §6), so the verdict "
                "holds for this pipeline only")
VOLUMES = f"on the volumetric clips (units: the vol_test_* clips; {PIXEL_FILTER})"
WRLS, RLS, SVGF, NOISY = (RowNeed("wrls", "wRLS"), RowNeed("rls", "RLS"), RowNeed("svgf", "SVGF"),
                          RowNeed("noisy", "noisy input"))
RAE = RowNeed("rae", "RAE carrying its recurrent state", (("reset_state_every_frame", None),))
TABLE_METHODS = ("noisy", "rae", "svgf", "wrls", "rls")
#: PSNR (dB) printed under the MANIX frames of the paper's Figs. 10-12 (one per scenario, 2 spp, 720p):
#: MC input, RAE, SVGF, wRLS.
PAPER_MANIX_PSNR = {"camera animation (Fig. 10)": (29.22, 35.96, 35.22, 35.62),
                    "moving light (Fig. 11)": (28.15, 35.86, 33.45, 33.54),
                    "transfer-function edit (Fig. 12)": (28.60, 36.19, 35.34, 36.23)}


def _row(res: Results, need: RowNeed) -> str | None:
    return res.row_of(need.method, **dict(need.params))


def decide_c41(res: Results) -> Decision:
    wrls, svgf = _row(res, WRLS), _row(res, SVGF)
    missing = spp_available(res, PAPER_SPP, [wrls, svgf])
    if missing:
        return not_run(missing)
    return Decision([compare_rows(res, wrls, svgf, "psnr", PAPER_SPP, "higher"),
                     compare_rows(res, wrls, svgf, "trmae", PAPER_SPP, "lower")], note=f"{PAPER_SPP} spp; {SURFACES}")


def decide_c42(res: Results) -> Decision:
    wrls, rls = _row(res, WRLS), _row(res, RLS)
    if res.robustness is None:
        return not_run("robustness scenario disabled (evaluation.robustness.enabled)")
    spp = res.cfg["evaluation"]["robustness"]["spp"]
    have = set(res.robustness.method_id)
    if wrls not in have or rls not in have:
        return not_run("no robustness results for wrls or rls")
    missing = spp_available(res, spp, [wrls, rls])
    if missing:
        return not_run(missing)
    spiked = {m: res.robustness[res.robustness.method_id == m].set_index("scene")["psnr_spiked"] for m in (wrls, rls)}
    drop = {m: res.scene_values(m, spp, "psnr") - spiked[m] for m in (wrls, rls)}
    return Decision([Part.paired(spiked[wrls], spiked[rls], "psnr", f"{wrls} spiked @ {spp} spp",
                                 f"{rls} spiked @ {spp} spp", "higher", rows=((wrls, spp), (rls, spp))),
                     Part.paired(drop[wrls], drop[rls], "psnr_drop", f"{wrls} drop", f"{rls} drop", "lower",
                                 rows=((wrls, spp), (rls, spp)))],
                    note="spikes (up to 500x the frame mean) and NaN/Inf injected into the noisy samples: needs "
                         f"higher PSNR and a smaller PSNR drop than RLS; {SURFACES}")


def decide_c43(res: Results) -> Decision:
    wrls, noisy = _row(res, WRLS), _row(res, NOISY)
    spps = list(res.cfg["evaluation"]["spp"])
    if len(spps) < 2:
        return not_run("needs two or more evaluated spp (RAE's gain at the lowest versus the highest)")
    # The RAE at each end is the one trained at that spp where a config has it (issue 46 §4): an RAE trained at
    # 1 spp and run at 4 is out of its training distribution, which alone shrinks its gain.
    rae_low, rae_high = row_at(res, RAE, spps[0]), row_at(res, RAE, spps[-1])
    missing = "; ".join(filter(None, [spp_available(res, s, [wrls, noisy]) for s in spps]
                               + [spp_available(res, spps[0], [rae_low]), spp_available(res, spps[-1], [rae_high])]))
    if missing:
        return not_run(missing)
    parts = [compare_rows(res, wrls, noisy, "psnr", s, "higher") for s in spps]
    parts.append(gain_part(res, res.claim_values_per_seed, rae_low, rae_high, noisy, spps[0], spps[-1]))
    return Decision(parts, note=f"wRLS above its input at every evaluated spp {spps}, and RAE's PSNR gain smaller "
                                f"at {spps[-1]} than at {spps[0]} spp ({_trained_at(res, rae_low, rae_high)}); "
                                f"{SURFACES}")


def _trained_at(res: Results, *rows: str) -> str:
    """'rae trained at 1 spp, rae_4spp trained at 4 spp' for the distinct rows."""
    return ", ".join(f"{row} trained at {training_spp(res.cfg, res.spec(row).params.get('model'))} spp"
                     for row in dict.fromkeys(rows))


def decide_c44(res: Results) -> Decision:
    from denoisers import registry

    wrls, rae = _row(res, WRLS), _row(res, RAE)
    missing = spp_available(res, PAPER_SPP, [wrls, rae])
    if missing:
        return not_run(missing)
    model = res.model_of(rae)
    facts = [Fact("wRLS needs no training", not registry.get("wrls").info.trainable),
             Fact("RAE is trained", registry.get("rae").info.trainable)]
    speed = compare_speed(res, wrls, rae, PAPER_SPP, "lower")
    if isinstance(speed, str):
        return not_run(speed)
    return Decision([speed], facts,
                    note=f"time per frame from the timing job ({res.timing.threads} thread(s), one scene, interleaved "
                         f"rounds); RAE {model.describe() if model else rae}")


def _volume_rows(res: Results, *needs: tuple[str, dict]) -> tuple[list[str | None], str]:
    """Volume row ids of (registry method, params) needs, and '' or why the claim cannot run on the volumes."""
    vol = res.volumes
    if vol is None:
        return [None] * len(needs), "no volumetric clips (volumes.enabled, volumes.n_test)"
    rows = [vol.row_of(method, **params) for method, params in needs]
    missing = [method for (method, _), row in zip(needs, rows) if row is None]
    if missing:
        reasons = [f"{r['id']} @ {r['spp']} spp: {r['reason']}" for r in vol.runs
                   if r["method"] in missing and r["status"] != "ran"]
        return rows, (f"no volume row of method {', '.join(missing)} ran on the clips ("
                      + ("; ".join(reasons) if reasons else "none in volumes.rows") + ")")
    return rows, ""


def _volume_part(res: Results, a: str, b: str, metric: str, spp: int, claimed: str,
                 at_half_budget: bool = False) -> Part:
    """Part a - b on the volumetric clips, seed-averaged, with its half-budget comparison when the rows have one."""
    vol = res.volumes
    part = Part.paired(vol.scene_values(a, spp, metric), vol.scene_values(b, spp, metric), metric,
                       f"{a} @ {spp} spp", f"{b} @ {spp} spp", claimed, rows=((a, spp), (b, spp)),
                       a_seeds=vol.scene_values_per_seed(a, spp, metric), b_seeds=vol.scene_values_per_seed(b, spp, metric),
                       seeds=seeds_of(vol, ((a, spp), (b, spp))))
    part.at_half_budget = at_half_budget
    half_a, half_b = vol.half_row(a, spp), vol.half_row(b, spp)
    if not at_half_budget and part.seeds and half_a and half_b:
        part.half = _volume_part(res, half_a, half_b, metric, spp, claimed, at_half_budget=True)
    return part


def gain_part(results: SeedAveraged, per_seed: Callable[[str, int, str], list[pd.Series]], rae_low: str,
              rae_high: str, noisy: str, low: int, high: int, at_half_budget: bool = False) -> Part:
    """Part 'RAE's PSNR gain over its input is smaller at ``high`` than at ``low`` spp' from per-seed per-scene
    values (``per_seed(row, spp, column)``), seed-averaged, with its half-budget comparison when the RAE rows have
    one. ``rae_low`` / ``rae_high`` are the RAE rows at each spp (the same row, or one trained at each spp)."""
    seed_gain = {s: seed_differences(per_seed(rae, s, "psnr"), per_seed(noisy, s, "psnr"))
                 for rae, s in ((rae_low, low), (rae_high, high))}
    gain = {s: seed_mean(seed_gain[s]) for s in (low, high)}
    rows = ((rae_low, low), (rae_high, high), (noisy, low), (noisy, high))
    part = Part.paired(gain[high], gain[low], "psnr", f"RAE gain over input @ {high} spp ({rae_high})",
                       f"RAE gain @ {low} spp ({rae_low})", "lower", rows=rows, a_seeds=seed_gain[high],
                       b_seeds=seed_gain[low], seeds=seeds_of(results, rows))
    part.at_half_budget = at_half_budget
    half_low, half_high = results.half_row(rae_low, low), results.half_row(rae_high, high)
    if not at_half_budget and part.seeds and half_low and half_high:
        part.half = gain_part(results, per_seed, half_low, half_high, noisy, low, high, at_half_budget=True)
    return part


def decide_c41_volumes(res: Results) -> Decision:
    (wrls, svgf), problem = _volume_rows(res, ("wrls", {"prefilter": None}), ("svgf_volume", {}))
    if problem:
        return not_run(problem)
    missing = [row for row in (wrls, svgf) if not res.volumes.ran(row, PAPER_SPP)]
    if missing:
        return not_run("; ".join(f"{row} @ {PAPER_SPP} spp {res.volumes.reason(row, PAPER_SPP)}" for row in missing))
    return Decision([_volume_part(res, wrls, svgf, "psnr", PAPER_SPP, "higher"),
                     _volume_part(res, wrls, svgf, "trmae", PAPER_SPP, "lower")],
                    note=f"{PAPER_SPP} spp, {VOLUMES}; SVGF without normals, with the clips' reprojection")


def decide_c42_volumes(res: Results) -> Decision:
    (wrls, rls), problem = _volume_rows(res, ("wrls", {"prefilter": None}), ("rls", {}))
    if problem:
        return not_run(problem)
    vol, spp = res.volumes, int(res.cfg["evaluation"]["robustness"]["spp"])
    if not res.cfg["evaluation"]["robustness"]["enabled"]:
        return not_run("spike scenario disabled (evaluation.robustness.enabled)")
    have = set() if vol.robustness is None else set(vol.robustness.method_id)
    missing = [row for row in (wrls, rls) if row not in have or not vol.ran(row, spp)]
    if missing:
        return not_run(f"no spike-scenario results on the clips at {spp} spp for {', '.join(missing)} (volumes.rows "
                       "entries with robustness: true)")
    spiked = {row: vol.robustness[vol.robustness.method_id == row].set_index("scene")["psnr_spiked"]
              for row in (wrls, rls)}
    drop = {row: vol.scene_values(row, spp, "psnr") - spiked[row] for row in (wrls, rls)}
    return Decision([Part.paired(spiked[wrls], spiked[rls], "psnr", f"{wrls} spiked @ {spp} spp",
                                 f"{rls} spiked @ {spp} spp", "higher"),
                     Part.paired(drop[wrls], drop[rls], "psnr_drop", f"{wrls} drop", f"{rls} drop", "lower")],
                    note=f"{VOLUMES}: spikes and NaN/Inf injected into the noisy samples (evaluation.robustness); needs "
                         "higher PSNR and a smaller PSNR drop than RLS")


def decide_c43_volumes(res: Results) -> Decision:
    (wrls, noisy), problem = _volume_rows(res, ("wrls", {"prefilter": None}), ("noisy", {}))
    if problem:
        return not_run(problem)
    spps = [int(s) for s in res.cfg["volumes"]["denoise_spp"]]
    missing = [f"{row} @ {s} spp" for s in spps for row in (wrls, noisy) if not res.volumes.ran(row, s)]
    if missing:
        return not_run("not run: " + ", ".join(missing))
    if len(spps) < 2:
        return not_run("needs two or more volumes.denoise_spp (RAE's gain at the lowest versus the highest)")
    # The paper's RAE is retrained on colour alone on volumetric clips (rae_color); a surface RAE row would
    # need normals the clips lack and never runs there.
    vol = res.volumes
    configured = [spec.id for method in RAE_VOLUME_METHODS for spec in vol.specs if spec.method == method]
    if not configured:
        return not_run("no RAE row on the volumetric clips: the paper's RAE is retrained colour-only on volumetric "
                       "clips (a volumes.rows entry of method rae_color whose model trains on them)")
    rae = next((row for row in configured if all(vol.ran(row, s) for s in (spps[0], spps[-1]))), configured[0])
    missing = [f"{rae} @ {s} spp {vol.reason(rae, s)}" for s in (spps[0], spps[-1]) if not vol.ran(rae, s)]
    if missing:
        return not_run("; ".join(missing))
    parts = [_volume_part(res, wrls, noisy, "psnr", s, "higher") for s in spps]
    parts.append(gain_part(vol, vol.scene_values_per_seed, rae, rae, noisy, spps[0], spps[-1]))
    return Decision(parts, note=f"{VOLUMES}: wRLS above its input at every spp {spps}, and RAE's PSNR gain smaller "
                                f"at {spps[-1]} than at {spps[0]} spp")


CLAIMS = (
    # The volume claims' rows are volumes.rows entries, which their decide functions look up (the claims table's
    # needs are surface rows).
    Claim("C4.1", PAPER, "wRLS beats SVGF in PSNR and flickers less (TRMAE) on volumetric sequences", (),
          decide_c41_volumes),
    Claim("C4.1s", PAPER, "(surfaces) wRLS beats SVGF in PSNR and flickers less (TRMAE)", (WRLS, SVGF), decide_c41),
    Claim("C4.2", PAPER, "wRLS is more robust to spike noise than plain RLS on volumetric sequences", (),
          decide_c42_volumes),
    Claim("C4.2s", PAPER, "(surfaces) wRLS is more robust to spike noise than plain RLS", (WRLS, RLS), decide_c42),
    Claim("C4.3", PAPER, "wRLS improves on its input at every spp on volumes, while RAE's gain shrinks as spp grows",
          (), decide_c43_volumes),
    Claim("C4.3s", PAPER, "(surfaces) wRLS improves on its input at every spp, while RAE's gain shrinks as spp grows",
          (WRLS, NOISY, RAE), decide_c43),
    Claim("C4.4", PAPER, "wRLS needs no training and runs faster than RAE", (WRLS, RAE), decide_c44),
)


def comparison_table(res: Results) -> pd.DataFrame:
    """Rows: the paper's methods that are configured; columns: PSNR, TRMAE, FLIP per evaluated spp."""
    import pandas as pd

    rows = []
    for spec in res.main_specs:
        if spec.method not in TABLE_METHODS or spec.params.get("reset_state_every_frame"):
            continue
        row: dict[str, Any] = {"method": spec.id}
        for metric in ("psnr", "trmae", "flip"):
            for spp in res.cfg["evaluation"]["spp"]:
                value = fmt_ci(*mean_ci(res.scene_values(spec.id, spp, metric).to_numpy(float))[:3], metric) \
                    if res.ran(spec.id, spp) else "not run"
                row[f"{LABELS[metric]} @ {spp} spp"] = value
        rows.append(row)
    return pd.DataFrame(rows)


VOLUME_METRICS = ("psnr", "ssim", "flip", "trmae", "tpsnr")


def volume_scenario_table(res: Results, spp: int = PAPER_SPP) -> pd.DataFrame:
    """Rows: every volume row; per scenario: the mean over its clips of PSNR, SSIM, FLIP, TRMAE and tPSNR at
    ``spp``; then PSNR over all clips with its 95 % interval ('not run' and the reason for rows that did not)."""
    import pandas as pd

    vol = res.volumes
    scenarios = list(dict.fromkeys(vol.scenarios.values()))
    rows = []
    for spec in vol.specs:
        row: dict[str, Any] = {"row": spec.id, "method": spec.method}
        if not vol.ran(spec.id, spp):
            row["note"] = vol.reason(spec.id, spp)
            rows.append(row)
            continue
        table = vol.per_scene[(vol.per_scene.method_id == spec.id) & (vol.per_scene.spp == spp)]
        for scenario in scenarios:
            mine = table[table.scenario == scenario]
            for metric in VOLUME_METRICS:
                row[f"{scenario}: {LABELS[metric]}"] = fmt_ci(float(mine[metric].mean()), float("nan"), float("nan"),
                                                             metric)
        psnr = table["psnr"].to_numpy(float)
        row[f"all {len(psnr)} clips: {LABELS['psnr']}"] = fmt_ci(*mean_ci(psnr)[:3], "psnr")
        row["note"] = ""
        rows.append(row)
    return pd.DataFrame(rows)


def volume_spp_table(res: Results) -> pd.DataFrame:
    """PSNR (mean over all clips, 95 % interval) of every volume row at every volumes.denoise_spp (Figs. 16-17)."""
    import pandas as pd

    vol = res.volumes
    rows = []
    for spec in vol.specs:
        row: dict[str, Any] = {"row": spec.id}
        for spp in res.cfg["volumes"]["denoise_spp"]:
            row[f"PSNR @ {spp} spp"] = (fmt_ci(*mean_ci(vol.scene_values(spec.id, spp, "psnr").to_numpy(float))[:3],
                                              "psnr") if vol.ran(spec.id, spp) else "not run")
        rows.append(row)
    return pd.DataFrame(rows)


def volume_brightness_table(res: Results) -> pd.DataFrame:
    """Bias in the dark half of every frame: the sum of the output over the sum of the reference radiance over the
    pixels whose reference luminance is below the frame's median (all frames of a clip, then the mean over the
    clips), per volume row and spp; 1 is unbiased, and the MC input's value shows the noise of the measure. wRLS
    brightens dark, sparse regions at 1-2 spp (denoisers/methods/rls.py); the row with the paper's Gaussian
    prefilter shows whether that step prevents it."""
    import numpy as np
    import pandas as pd

    from denoisers.evaluate import read_frame_files, read_radiance_exr
    from denoisers.filters import REC709_LUMINANCE
    from denoisers.jobs.volumes import volume_denoised_dir
    from scenegen.dataset import find_frames, load_reference_frame

    vol = res.volumes
    dark = {}          # (scene, frame) -> (reference (3, H, W), dark mask (H, W))
    for scene in vol.scenes:
        for t, path in find_frames(res.results_dir / "renders" / scene / "reference").items():
            reference = load_reference_frame(path, ["radiance"])[0]["radiance"]
            lum = np.tensordot(np.asarray(REC709_LUMINANCE), reference, axes=1)          # (H, W)
            dark[scene, t] = reference, lum < np.median(lum)
    rows = []
    for spec in vol.specs:
        row: dict[str, Any] = {"row": spec.id}
        for spp in res.cfg["volumes"]["denoise_spp"]:
            column = f"dark half: output / reference @ {spp} spp"
            if not vol.ran(spec.id, spp):
                row[column] = "not run"
                continue
            ratios = []
            for scene in vol.scenes:
                out_sum = ref_sum = 0.0
                for t, path in read_frame_files(volume_denoised_dir(res.results_dir, spec.id, scene, spp)).items():
                    reference, mask = dark[scene, t]
                    out_sum += float(read_radiance_exr(path)[:, mask].sum())
                    ref_sum += float(reference[:, mask].sum())
                ratios.append(out_sum / max(ref_sum, 1e-12))
            row[column] = f"{np.mean(ratios):.3f}"
        rows.append(row)
    return pd.DataFrame(rows)


def _tables(cfg: dict) -> list[str]:
    volumes = cfg.get("volumes") or {}
    have = volumes.get("enabled", False) and int(volumes.get("n_test", 0)) > 0
    return ["iglesias_comparison"] + (["iglesias_volumes", "iglesias_volumes_spp", "iglesias_volumes_brightness"]
                                      if have else [])


def _figures(cfg: dict) -> list[str]:
    return ["iglesias_volume_curves", "iglesias_volume_grid"] if len(_tables(cfg)) > 1 else []


def write(res: Results, tables: Path, figures: Path) -> str:
    from denoisers.report.tables import write_table
    from denoisers.reproductions._iglesias2022_figures import plot_curves, plot_grid

    import pandas as pd

    paper = pd.DataFrame([{"scenario (MANIX)": name, **dict(zip(("MC input", "RAE", "SVGF", "wRLS"), values))}
                          for name, values in PAPER_MANIX_PSNR.items()])
    lines = []
    if res.volumes is not None:
        vol = res.volumes
        per_scenario = volume_scenario_table(res)
        by_spp = volume_spp_table(res)
        write_table(per_scenario, tables, "iglesias_volumes", frame_to_markdown(per_scenario))
        write_table(by_spp, tables, "iglesias_volumes_spp", frame_to_markdown(by_spp))
        brightness = volume_brightness_table(res)
        write_table(brightness, tables, "iglesias_volumes_brightness", frame_to_markdown(brightness))
        curves = plot_curves(vol, PAPER_SPP, figures / "iglesias_volume_curves.png")
        grid = plot_grid(vol, res.results_dir, PAPER_SPP, figures / "iglesias_volume_grid.png")
        counts = ", ".join(f"{sum(1 for k in vol.scenarios.values() if k == scenario)} {scenario}"
                           for scenario in dict.fromkeys(vol.scenarios.values()))
        lines += [f"### Volumetric clips ({len(vol.scenes)} test clips: {counts})", "",
                  f"Every volume row (volumes.rows) on the vol_test_* clips at {PAPER_SPP} spp (per scenario: mean over "
                  "its clips; all clips: mean and 95 % interval). FLIP and SSIM stand in for LPIPS.", "",
                  frame_to_markdown(per_scenario), "", "PSNR at every denoised spp (the paper's Figs. 16-17):", "",
                  frame_to_markdown(by_spp), "",
                  "Bias in the dark half of each frame (pixels below the reference's median luminance): output over "
                  "reference radiance, 1 = unbiased; the MC input shows the measure's noise. wRLS is known to "
                  "brighten dark, sparse regions at 1-2 spp; the paper's Gaussian prefilter is its remedy:", "",
                  frame_to_markdown(brightness), "",
                  f"Per-frame PSNR per scenario: `figures/iglesias_volume_curves.png`{' (' + curves + ')' if curves else ''}; "
                  f"last frames: `figures/iglesias_volume_grid.png`{' (' + grid + ')' if grid else ''}.", ""]
    table = comparison_table(res)
    markdown = frame_to_markdown(table) if len(table) else "none of the paper's methods is configured\n"
    write_table(table, tables, "iglesias_comparison", markdown)
    lines += ["### Surface scenes", "", f"MC input, RAE, SVGF, (w)RLS {SURFACES} (FLIP in place of LPIPS).", "",
              markdown, "", "Paper (PSNR in dB of single MANIX frames in Figs. 10-12, volumes, 2 spp, 720p; for "
              "context only):", "", frame_to_markdown(paper)]
    return "\n".join(lines)


REPRODUCTION = Reproduction(
    key="iglesias2022", paper="Iglesias-Guitian et al. 2022", order=4,
    title="Real-time denoising of volumetric path tracing for direct volume rendering (wRLS)",
    source="iglesias-guitian2022-wrls-volumetric.txt", claims=CLAIMS,
    tables=_tables, figures=_figures, write=write)
