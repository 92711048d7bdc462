"""The models of an evaluation: resolving specs, and the settings each is scored in.

Split from :mod:`mehs.ssr.scoring` (which uses everything here): :func:`resolve_models`
loads the specs (a bare ``regression`` is fitted here), :func:`defined_settings` drops the
settings a model's prediction has no defined meaning in, :func:`predict_setting` runs one
setting, :func:`evaluation_notes` says why a model is not scored somewhere.
"""

from __future__ import annotations

from typing import Any

import numpy as np

from mehs.errors import InputError
from mehs.ssr.contract import applies_preprocessing, trained_for
from mehs.ssr.data import PairSet, load_pairs
from mehs.ssr.pipeline import predict
from mehs.ssr.preprocess import Preprocessing
from mehs.ssr.protocol import PREPROCESS_CHOICES, model_settings, preprocessing_for, protocol_notes


def fit_regressions(pairs: PairSet, label: str, pp: tuple, ins: tuple, default_pp: Preprocessing,
                     seed: int) -> list[tuple[Any, str]]:
    """A bare ``regression``: one fit per requested pre-processing setting, as the paper
    trains one network per setting; all share the row ``label``."""
    from mehs.ssr.baselines import fit_regression_baseline

    train_ids = (pairs.splits or {}).get("train") or []
    if pairs.manifest is None or not train_ids:
        raise InputError("the 'regression' baseline needs a train split to fit on; run "
                         "'mehs train-baseline' and pass the .npz instead", pairs.root)
    kind = "hdr" if "hdr" in ins else "ldr"
    train = load_pairs(pairs.root, split="train")
    out = []
    for p in pp:
        spec = default_pp if p == "on" else None
        model = fit_regression_baseline(train, seed=seed, input=kind, preprocessing=spec)
        model.name = label
        out.append((model, f"fitted on the train split ({len(train_ids)} scenes, "
                           f"{kind.upper()}, {spec.label() if spec else 'no pre-processing'})"))
    return out


def resolve_models(models, pairs: PairSet, *, seed: int = 0, pp: tuple = PREPROCESS_CHOICES,
                    ins: tuple = ("hdr",), default_pp: Preprocessing | None = None
                    ) -> list[tuple[Any, str, str]]:
    """Load each spec (``NAME=SPEC`` names the row); a bare ``regression`` is fitted here."""
    from mehs.ssr.models import load_model, split_named_spec

    default_pp = default_pp or Preprocessing()
    if isinstance(models, str):
        models = [m for m in models.split(",") if m.strip()]
    resolved: list = []
    names: dict[str, set] = {}
    for spec in models:
        label = None
        if isinstance(spec, str):
            label, spec = split_named_spec(spec.strip())
        if isinstance(spec, str) and spec.strip().lower() == "regression":
            group = fit_regressions(pairs, label or "regression", pp, ins, default_pp, seed)
        else:
            model = load_model(spec)
            if label:
                model.name = label
            group = [(model, str(getattr(model, "description", "")))]
        base = label or str(getattr(group[0][0], "name", spec))
        mine = {x for m, _ in group for x in model_settings(m, ins, pp, (True, False))}
        name, k = base, 2
        while name in names:
            if label and not (names[name] & mine):
                break  # one row, several models each trained for other settings (the paper's)
            if label:
                raise InputError(f"two models are named {label!r} and were trained for the "
                                 "same setting; give each row its own name")
            name = f"{base}_{k}"
            k += 1
        names[name] = names.get(name, set()) | mine
        for model, note in group:
            resolved.append((model, name, note))
    if not resolved:
        raise InputError("no models given")
    return resolved


def predict_setting(model, tf, rgb: np.ndarray, preprocess: str, restore: bool,
                     default_pp: Preprocessing, wl: np.ndarray):
    """:func:`mehs.ssr.pipeline.predict` in one setting, ``(cube, stats)``.

    Restoration off with pre-processing on: ``predict`` maps the output back with
    the inverse Reinhard, which is right for a *fixed* method run on tone-mapped
    RGB (Smits then returns a tone-mapped spectrum) but not for a model *fitted*
    on pre-processed input: it was fitted to the ground-truth spectra, so its
    output already is one (the inverse sent a Reinhard-fitted regression's MRAE
    from 0.7 to 4·10⁶: spectra above 1 clip at the operator's pole). Such a model
    gets the pre-processed RGB and its output is taken as is.
    """
    spec = preprocessing_for(tf, preprocess, default_pp)
    if (spec is not None and not restore and tf.declared and not tf.fixed
            and not applies_preprocessing(model)):
        return predict(model, spec(rgb), restore=False, wavelengths=wl, return_stats=True)
    return predict(model, rgb, restore=restore, wavelengths=wl, return_stats=True,
                   preprocessing=spec)


#: Why an undeclared model is not scored with pre-processing on and restoration off.
UNDEFINED_SETTING = ("its output with pre-processing on and restoration off is undefined for "
                     "a model that declares nothing: a tone-mapped spectrum would need the "
                     "inverse Reinhard, an absolute one none, and mehs cannot tell which")


def defined_settings(model, settings: list[tuple[str, str, bool]]) -> list[tuple[str, str, bool]]:
    """``settings`` less those in which ``model``'s prediction has no defined meaning.

    With pre-processing on and restoration off, :func:`mehs.ssr.pipeline.predict` maps the
    output back with the inverse Reinhard (right for a fixed method, whose output is then
    tone-mapped), and a fitted model declaring its training takes its output as is
    (:func:`predict_setting`). The paper scores only declared models, each in the setting
    it was trained for (§3.6, §4: "–" elsewhere), so for a model that declares nothing
    either choice is a guess; the inverse gave a linear end-to-end function MRAE 149
    where its other three settings gave about 1. Such a row is shown as "–" with a note.
    """
    if trained_for(model).declared:
        return settings
    return [st for st in settings if not (st[1] == "on" and not st[2])]


def evaluation_notes(resolved, ins, pp, rs, fixed_preprocess: bool, undefined: list[str]) -> list[str]:
    """:func:`mehs.ssr.protocol.protocol_notes`, with the setting an undeclared model is not
    scored in (:func:`defined_settings`) said instead of "every requested setting"."""
    notes = protocol_notes(resolved, ins, pp, rs, fixed_preprocess=fixed_preprocess)
    for name in dict.fromkeys(undefined):
        every = f"{name} declares no trained input: scored under every requested setting"
        notes = [n for n in notes if n != every]
        notes.append(f"{name} declares no trained input: scored under every requested "
                     f"setting but pre-processing on with restoration off ('–': "
                     f"{UNDEFINED_SETTING}; declare what it was trained for: a trained_for "
                     f"attribute, or a <model file>.json sidecar)")
    return notes
