"""The evaluation protocol: under which settings each model is scored (paper §4).

A *setting* is ``(input, preprocess, restore)`` with input ``"hdr"``/``"ldr"``,
preprocess ``"on"``/``"off"`` and restore ``True``/``False``. The paper trains one
network per pre-processing setting and shows "–" where a method was not
trained; :func:`allowed` is that rule, from the model's
:class:`~mehs.ssr.contract.TrainedFor`:

- **pre-processing**: on exactly when the model was trained with it, and then
  with *its* recorded :class:`~mehs.ssr.preprocess.Preprocessing`. Fixed
  baselines (nothing trained) are off, and on too only when the user asks
  (``fixed_preprocess``), with the evaluation's :class:`Preprocessing`.
- **restoration**: on for a model predicting a shape (◇), off for an
  end-to-end one (its output *is* the spectrum), as requested for baselines
  whose output is meaningful both ways.
- **input**: a model trained on HDR is scored on HDR and on LDR input (the
  paper's Table 4: LDR-RGB into networks trained with HDR images); one trained
  on LDR only on LDR; untrained ones on both.
- Models that declare nothing are scored under every requested setting.
"""

from __future__ import annotations

from typing import Any

from mehs.ssr.contract import TrainedFor, trained_for
from mehs.ssr.preprocess import Preprocessing

PREPROCESS_CHOICES = ("off", "on")


def allowed(tf: TrainedFor, input: str, preprocess: str, restore: bool, *,
            fixed_preprocess: bool = False) -> str | None:
    """``None`` if a model declaring ``tf`` is scored in this setting, else the reason it is not."""
    if not tf.declared:
        return None
    if tf.input == "ldr" and input != "ldr":
        return "trained on LDR input only"
    if tf.fixed:
        if preprocess == "on" and not fixed_preprocess:
            return "fixed method: no pre-processing unless asked (--fixed-preprocess)"
    elif (preprocess == "on") != (tf.preprocessing is not None):
        return ("trained with " + tf.preprocessing.label() if tf.preprocessing
                else "trained without pre-processing")
    if tf.output == "shape" and not restore:
        return "predicts a spectral shape: scored with luminance restoration"
    if tf.output == "spectra" and restore:
        return "end to end: scored without luminance restoration"
    return None


def preprocessing_for(tf: TrainedFor, preprocess: str, default: Preprocessing) -> Preprocessing | None:
    """The :class:`Preprocessing` to apply in setting ``preprocess`` (``None`` when off)."""
    if preprocess != "on":
        return None
    return tf.preprocessing if tf.preprocessing is not None else default


def model_settings(model: Any, inputs, preprocess, restore, *,
                   fixed_preprocess: bool = False) -> list[tuple[str, str, bool]]:
    """The settings ``model`` is scored under (in request order).

    ``restore`` applies to models whose output allows both; a shape model is
    always restored and an end-to-end one never, whatever was requested, so
    each is scored in its own setting rather than dropped.
    """
    tf = trained_for(model)
    if tf.declared and tf.output == "shape":
        restore = (True,)
    elif tf.declared and tf.output == "spectra":
        restore = (False,)
    return [(i, p, r) for i in inputs for p in preprocess for r in restore
            if allowed(tf, i, p, r, fixed_preprocess=fixed_preprocess) is None]


def protocol_notes(resolved: list[tuple[Any, str, str]], inputs, preprocess, restore, *,
                   fixed_preprocess: bool = False) -> list[str]:
    """One note per model that is not scored in some requested setting, saying why."""
    notes = []
    for model, name, _ in resolved:
        tf = trained_for(model)
        if not tf.declared:
            notes.append(f"{name} declares no trained input: scored under every requested setting")
            continue
        why = sorted({allowed(tf, i, p, r, fixed_preprocess=fixed_preprocess)
                      for i in inputs for p in preprocess for r in restore} - {None})
        if why:
            notes.append(f"{name} ({tf.label()}): '–' where {'; '.join(why)}")
    return notes
