"""Settings digests: which config settings every output of an experiment was computed from.

An experiment is one config with its own folder (config key ``output_dir``). Within a folder, outputs
can still come from different settings, e.g. an interrupted ``--config seed=7`` run followed by stage
targets of the default config. Every output therefore records a digest of the settings it came from,
and the report refuses to combine outputs whose digests disagree with the config it is built for.

Two kinds of digests (SHA-256 of canonical JSON, scenegen.config.config_digest):

* job digests (``scene_digest``, ``render_digest``, ``denoise_digest``, ...): the config keys one job's
  output depends on besides its input files. The workflow passes them as params, so Snakemake reruns a
  job when they change (workflow/rules/common.smk).
* lineage digests (:class:`Lineage`): a job's own digest combined with those of everything upstream of
  it (scene, renders, model, tuning), in the recorded form (scenegen.config.short_digest). They are
  recorded in timing.json (denoised clips), the JSON sidecar of every metrics CSV (spp{spp}.json), the
  robustness summary.json, every model's summary.json and every tuning result. Keys that only say how many scenes or
  rows exist (scenes.n_test, other evaluation rows) are in no clip's lineage, so adding a scene or a row
  never flags existing outputs; the seed, scene and render settings are in all of them.

Config level only (no torch): the Snakefile calls the job digests while it is parsed.
"""
from __future__ import annotations

from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, Protocol

from denoisers.training.models import method_model, model_spec, settings_digest, training_split
from denoisers.jobs.tuning import TUNED_KEY, tuning_entry
from scenegen.config import config_digest, short_digest
# The scene and render digests live with the scene generator (the training job needs them too); re-exported.
from scenegen.digests import (NOISY_ONLY_KEYS, REFERENCE_ONLY_KEYS, SCENE_LAYOUT_KEYS, render_digest,  # noqa: F401
                              scene_digest, scene_settings)

#: Key of the recorded digest in timing.json, the metrics sidecars, summary.json and tuning results.
DIGEST_KEY = "settings_digest"
class SettingsMismatchError(ValueError):
    """Outputs were computed from other settings than the config at hand (their digests disagree)."""


class RowSpec(Protocol):
    """What the digests need of an evaluation row (denoisers.evaluate.MethodSpec)."""

    method: str
    params: dict[str, Any]


# ---------------------------------------------------------------------------------------- job digests
def _row_settings(spec: RowSpec) -> dict[str, Any]:
    return {"method": spec.method, "params": spec.params}


def denoise_digest(cfg: dict, spec: RowSpec) -> str:
    """Rule denoise_row (each clip): the row's method and parameters, torch threads and the out-of-range factor."""
    settings = {key: cfg["evaluation"][key] for key in ("threads", "out_of_range_factor")}
    return config_digest({**_row_settings(spec), **settings})


def evaluate_digest(cfg: dict) -> str:
    """Rule evaluate_row (each clip)."""
    return config_digest({"warmup_frames": cfg["evaluation"]["warmup_frames"]})


def robustness_digest(cfg: dict, spec: RowSpec) -> str:
    """Rule robustness_row (each clip; the injected corruption depends on the global seed)."""
    settings = {key: cfg["evaluation"][key] for key in ("robustness", "warmup_frames", "threads", "out_of_range_factor")}
    return config_digest({**_row_settings(spec), **settings, "seed": cfg["seed"]})


def train_digest(cfg: dict, model_id: str) -> str:
    """Rule train_denoiser: the model's settings and what its training data depend on."""
    from denoisers.training.digests import data_settings

    spec = model_spec(cfg, model_id)
    return settings_digest(spec, data_settings(cfg, spec))


def tuning_digest(cfg: dict, method: str) -> str:
    """Rule tune_method: the shared tuning settings and the method's entry (its grid)."""
    settings = {key: value for key, value in cfg["tuning"].items() if key != "methods"}
    return config_digest({**settings, **tuning_entry(cfg, method)})


def training_speed_digest(cfg: dict) -> str:
    """Rule time_training: training.speed (threads resolved) and the timed models' settings but their budgets
    (what their step computes; the synthetic batch needs no data)."""
    from denoisers.training.speed import speed_models, speed_settings

    settings = {key: value for key, value in speed_settings(cfg).items() if key != "enabled"}
    models = [{key: value for key, value in spec.settings().items() if key != "budget"} for spec in speed_models(cfg)]
    return config_digest({"speed": settings, "models": models})


def report_digest(cfg: dict) -> str:
    """Rule build_report: the report states the whole configuration (but the ``stability`` section, whose
    scenario clips the report does not read, ``store``, which says where models come from, not what they are:
    a model's own digests cover that, and ``description``, a label that no rule reads). ``training.seeds`` and ``training.half_budget`` enter only when they add
    trainings (seeds above 1, half_budget true), so configs written before the keys existed keep their reports."""
    reported = {key: value for key, value in cfg.items() if key not in ("stability", "store", "description")}
    training = reported.get("training")
    if isinstance(training, dict):
        neutral = {key for key, value in (("seeds", 1), ("half_budget", False)) if training.get(key, value) == value}
        reported["training"] = {key: value for key, value in training.items() if key not in neutral}
    return config_digest(reported)


# ------------------------------------------------------------------------------------ lineage digests
class Lineage:
    """Lineage digests (recorded form) of one config's outputs; model and tuning digests are cached."""

    def __init__(self, cfg: dict) -> None:
        self.cfg = cfg
        self._cache: dict[tuple[str, str], str] = {}

    def model(self, model_id: str) -> str:
        """A trained model (models/{id}/summary.json): train_digest covers the data settings."""
        key = ("model", model_id)
        if key not in self._cache:
            self._cache[key] = short_digest(train_digest(self.cfg, model_id))
        return self._cache[key]

    def tuning(self, method: str) -> str:
        """A tuning result (tuning/{method}.json): its settings and the renders of the training scenes."""
        key = ("tuning", method)
        if key not in self._cache:
            scenes = sum(training_split(self.cfg), [])
            data = {scene: [render_digest(self.cfg, scene, kind) for kind in ("noisy", "reference")] for scene in scenes}
            self._cache[key] = short_digest(config_digest({"tuning": tuning_digest(self.cfg, method), "data": data}))
        return self._cache[key]

    def _row(self, spec: RowSpec) -> dict[str, str | None]:
        model = method_model(spec.params)
        return {"model": self.model(model) if model else None,
                "tuning": self.tuning(spec.method) if spec.params.get(TUNED_KEY) else None}

    def _clip(self, scene: str, *kinds: str) -> dict[str, str]:
        return {"scene": scene_digest(self.cfg, scene), **{kind: render_digest(self.cfg, scene, kind) for kind in kinds}}

    def denoised(self, spec: RowSpec, scene: str, spp: int) -> str:
        """A denoised clip (denoised/{row}/{scene}/spp{spp}/timing.json)."""
        return short_digest(config_digest({"denoise": denoise_digest(self.cfg, spec), "spp": int(spp),
                                           **self._row(spec), **self._clip(scene, "noisy")}))

    def metrics(self, spec: RowSpec, scene: str, spp: int) -> str:
        """A per-frame metrics CSV (metrics/{row}/{scene}/spp{spp}.csv; recorded in its .json sidecar)."""
        return short_digest(config_digest({"denoised": self.denoised(spec, scene, spp),
                                           "reference": render_digest(self.cfg, scene, "reference"),
                                           "evaluate": evaluate_digest(self.cfg)}))

    def timing(self, scene: str, runs: list[tuple[RowSpec, int]]) -> str:
        """The timing job (timing/timing.json): its settings and the denoised digests of the (row, spp) it
        times (denoisers.jobs.timing.timed_runs)."""
        settings = {key: value for key, value in self.cfg["evaluation"].get("timing", {}).items() if key != "enabled"}
        rows = [self.denoised(spec, scene, spp) for spec, spp in runs]
        return short_digest(config_digest({"timing": settings, "scene": scene, "rows": rows}))

    def training_speed(self) -> str:
        """The training-speed job (timing/training.json)."""
        return short_digest(training_speed_digest(self.cfg))

    def robustness(self, spec: RowSpec, scene: str, spp: int) -> str:
        """A robustness output (robustness/{row}/{scene}/spp{spp}/summary.json)."""
        return short_digest(config_digest({"robustness": robustness_digest(self.cfg, spec), "spp": int(spp),
                                           **self._row(spec), **self._clip(scene, "noisy", "reference")}))


# ------------------------------------------------------------------------------------------ checking
def mismatch_line(path: Path | str, recorded: str, expected: str) -> str:
    return f"{path}: recorded settings digest {recorded}, this config's is {expected}"


def check_recorded(path: Path | str, recorded: str | None, expected: str) -> None:
    """SettingsMismatchError if ``path`` records a digest other than ``expected`` (None: nothing recorded)."""
    if recorded is not None and recorded != expected:
        raise SettingsMismatchError(f"{mismatch_line(path, recorded, expected)}: it was computed from other "
                                    "settings (rerun its job, or remove it)")


@dataclass
class DigestLedger:
    """The digests of every output a report reads: matching, disagreeing, or not recorded (older outputs)."""

    matched: int = 0
    mismatched: list[str] = field(default_factory=list)
    unrecorded: list[str] = field(default_factory=list)

    def add(self, path: Path | str, recorded: Any, expected: str) -> None:
        if not isinstance(recorded, str) or not recorded:
            self.unrecorded.append(str(path))
        elif recorded == expected:
            self.matched += 1
        else:
            self.mismatched.append(mismatch_line(path, recorded, expected))

    def raise_if_mixed(self, cfg: dict, results_dir: Path) -> None:
        """Refuse to combine outputs computed from other settings, naming every one."""
        if not self.mismatched:
            return
        shown = self.mismatched[:30]
        more = [f"... and {len(self.mismatched) - len(shown)} more"] if len(self.mismatched) > len(shown) else []
        raise SettingsMismatchError(
            f"{len(self.mismatched)} output(s) under {results_dir} were computed from other settings than this "
            f"config (seed {cfg['seed']}, {cfg.get('description', 'no description')!r}); the report does not "
            "combine them:\n  - " + "\n  - ".join(shown + more) + "\nRerun their jobs with this config (the "
            "workflow reruns jobs whose settings changed; or --forcerun <rule>), or remove the experiment's outputs "
            "(python -m denoisers clean --config <config file>).")

    def summary(self) -> str:
        """One line for REPORT.md."""
        text = f"{self.matched} outputs record this config's settings digests"
        if self.unrecorded:
            text += (f"; {len(self.unrecorded)} record none (written before digests were recorded, unchecked), "
                     f"e.g. {self.unrecorded[0]}")
        return text
