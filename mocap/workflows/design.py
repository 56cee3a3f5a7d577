"""What ``mocap design --method model`` reads and writes: the identified face model of a session
(and a file holding it, so that repeated designs and refinements need not identify it again), a
design's reference, the played take of a refinement, and the closed-loop check on the virtual
face of a simulated session.
"""

from __future__ import annotations

import json
from dataclasses import dataclass
from pathlib import Path

import numpy as np
import pandas as pd

from mocap.analysis.model.face_model import FaceModel
from mocap.analysis.design.model_based import Reference
from mocap.core.session import SessionError


def paper_responses(source, dus, progress=None) -> dict:
    """Each DU's paper sigmoids (:class:`mocap.analysis.design.inverse_response.SigmoidPair`), what ``mocap design
    --method paper`` inverts: read from ``source``/properties.csv of a 'mocap run' output, or
    identified from a session in a temporary run (the sigmoids only: no recording, no bootstrap
    intervals; removed afterwards). The along-path columns where the output has them (the
    face's response in command units with little noise bias, docs/indices.md), the paper's
    literal ones otherwise (outputs written before they existed). ``progress``: str -> None.
    Raises ValueError naming the file when a DU has no identified response."""
    import tempfile

    from mocap.analysis.design.inverse_response import SigmoidPair

    source = Path(source)
    props_path = source / "properties.csv"
    if props_path.is_file():
        props = pd.read_csv(props_path).set_index("du")
    else:
        from mocap.workflows.run.pipeline import run_session
        from mocap.workflows.run.settings import RunSettings

        with tempfile.TemporaryDirectory(prefix="mocap-design-") as work:
            if progress:
                progress(f"identifying the responses of {source}")
            run_session(source, work, progress=progress,
                        settings=RunSettings(recording=False, bootstrap_samples=0))
            props = pd.read_csv(Path(work) / "properties.csv").set_index("du")
        props_path = source / "session.toml"
    missing = [d for d in dus if d not in props.index]
    if missing:
        raise ValueError(f"{props_path}: no identified response for DUs {missing} "
                         f"(has {sorted(props.index)})")
    suffix = "_along_path" if "alpha_fwd_along_path" in props.columns else ""
    return {d: SigmoidPair(*(props.loc[d, f"{k}{suffix}"]
                             for k in ("alpha_fwd", "beta_fwd", "alpha_bwd", "beta_bwd")))
            for d in dus}


def identify_model(path, effects=None, jobs: int = 1, progress=None) -> tuple[FaceModel, str]:
    """The identified face model of a session or a `mocap run` output folder.

    effects : None runs the discrepancy workflow (the paper's model plus every effect it names);
        a list of effect names fits exactly those (``hysteresis`` and ``curvature`` per curve,
        the others' global parameters by their profiles, in the order given).

    Returns (model, how it was identified).
    """
    from mocap.analysis.discrepancy.prepare import prepare
    from mocap.analysis.discrepancy.settings import DiscrepancySettings
    from mocap.analysis.discrepancy.workflow import run_discrepancy
    from mocap.analysis.model.effects import CATALOGUE
    from mocap.analysis.model.fit import fit_curves
    from mocap.analysis.model.profiles import profile_effect
    from mocap.workflows.discrepancy.inputs import load_measured

    say = progress or (lambda m: None)
    names = None if effects is None else list(effects)
    bad = [n for n in names or () if n not in CATALOGUE]
    if bad:  # before the session is read and prepared
        raise ValueError(f"--effects: unknown {', '.join(bad)} (known: {', '.join(CATALOGUE)})")
    ms = load_measured(path, progress=say)
    settings = DiscrepancySettings(jobs=jobs)
    prep = prepare(ms.session.fps, ms.marker_names, ms.rest_mm, ms.takes, ms.rest_X, settings)
    if names is None:
        res = run_discrepancy(prep, settings, progress=say)
        named = ", ".join(res.named) or "no missing effect"
        return res.final_model, f"discrepancy workflow on {ms.source} (named: {named})"
    data = prep.data
    takes = list(range(len(data.takes)))
    per_curve = [CATALOGUE[n]() for n in names if CATALOGUE[n].per_curve]
    model = fit_curves(data, tuple(per_curve), takes)
    for n in names:
        if not CATALOGUE[n].per_curve:
            model = profile_effect(data, model, CATALOGUE[n](), takes).model
            say(f"  {n}: {model.effect(n).describe()['value']:.4g} {CATALOGUE[n].unit}")
    return model, f"effects {', '.join(names)} fitted on {ms.source}"


MODEL_FILE_FORMAT = "facemocap face model 1"  # the first record of a model file


def save_model(model: FaceModel, path, source=None) -> Path:
    """Write an identified model to ``path`` (atomically), for :func:`load_model`.

    The file is a Python pickle of the :class:`FaceModel` after a format line, then the session
    it was identified on (``source``: a session or a 'mocap run' output; its folder and identity,
    :func:`mocap.workflows.design_loop.session_identity`; read by :func:`model_file_session`).
    Like an output folder's state files it is trusted; never load one from an untrusted source.
    """
    import pickle

    from mocap.core.atomic import atomic_path

    info = None
    if source is not None:
        from mocap.workflows.design_loop import _session_dir, session_identity

        info = {"session": str(_session_dir(source).resolve()),
                "session_sha256": session_identity(source)}
    with atomic_path(path) as tmp:
        with open(tmp, "wb") as f:
            pickle.dump(MODEL_FILE_FORMAT, f, protocol=pickle.HIGHEST_PROTOCOL)
            pickle.dump(model, f, protocol=pickle.HIGHEST_PROTOCOL)
            pickle.dump(info, f, protocol=pickle.HIGHEST_PROTOCOL)
    return Path(path)


def model_file_session(path) -> dict | None:
    """The session a model file's model was identified on ({"session": folder, "session_sha256":
    identity}), or None when the file does not record one."""
    import pickle

    load_model(path)
    try:
        with open(path, "rb") as f:
            pickle.load(f)
            pickle.load(f)
            info = pickle.load(f)
    except (EOFError, pickle.UnpicklingError):
        return None
    return info if isinstance(info, dict) else None


def load_model(path) -> FaceModel:
    """The model :func:`save_model` wrote to ``path``; ValueError if the file is not one."""
    import pickle

    try:
        with open(path, "rb") as f:
            head = pickle.load(f)
            model = pickle.load(f) if head == MODEL_FILE_FORMAT else None
    except (EOFError, pickle.UnpicklingError, AttributeError, ImportError, TypeError,
            ValueError, IndexError):
        head = model = None
    if head != MODEL_FILE_FORMAT or not isinstance(model, FaceModel):
        raise ValueError(f"{path}: expected a face model file written by 'mocap design "
                         f"--save-model' ({MODEL_FILE_FORMAT}), got something else; identify the "
                         "model again (without --model)")
    return model


@dataclass(frozen=True)
class PlayedTake:
    """A played take: its commands, its measured positions (n_frames, M, 3) mm and marker names."""

    name: str
    rows: pd.DataFrame
    X: np.ndarray
    marker_names: tuple[str, ...]
    fps: float


def played_take(path, take: str) -> PlayedTake:
    """Take ``take`` of a session or a `mocap run` output folder (SessionError names what is missing)."""
    from mocap.workflows.discrepancy.inputs import load_measured

    ms = load_measured(path)
    for t in ms.takes:
        if t.name == take:
            return PlayedTake(t.name, t.rows, t.X, ms.marker_names, ms.session.fps)
    raise SessionError(f"{path}: no commanded take {take!r} (takes: "
                       f"{', '.join(t.name for t in ms.takes)})")


def reference_path(commands_path) -> Path:
    """Where a design's reference is written next to its command file (``X.csv`` -> ``X.reference.csv``)."""
    p = Path(commands_path)
    return p.with_name(p.stem + ".reference.csv")


def write_reference(path, ref: Reference, marker_names) -> Path:
    """The reference as CSV: time_s and one column per marker (or a single column P)."""
    from mocap.core.atomic import write_csv

    cols = {"time_s": ref.t_s}
    if ref.r.ndim == 1:
        cols["P"] = ref.r
    else:
        cols.update({str(n): ref.r[:, m] for m, n in enumerate(marker_names)})
    write_csv(pd.DataFrame(cols), path, decimals=6)
    return Path(path)


def read_reference(path, plan_ref: Reference, marker_names) -> Reference:
    """A reference written by :func:`write_reference`, with ``plan_ref``'s windows."""
    df = pd.read_csv(path)
    if "time_s" not in df.columns:
        raise ValueError(f"{path}: expected a time_s column (a design's .reference.csv)")
    t = df["time_s"].to_numpy(float)
    if "P" in df.columns:
        r = df["P"].to_numpy(float)
    else:
        missing = [n for n in marker_names if n not in df.columns]
        if len(missing) == len(marker_names):
            raise ValueError(f"{path}: none of the model's markers is a column")
        r = np.column_stack([df[n].to_numpy(float) if n in df.columns else np.full(t.size, np.nan)
                             for n in marker_names])
    return Reference(t, r, np.interp(t, plan_ref.t_s, plan_ref.ideal), plan_ref.rise,
                     plan_ref.fall, plan_ref.start_s, plan_ref.end_s, plan_ref.label)


# ----------------------------------------------------------------------------------------------
# closed loop on the virtual face


def virtual_face_of(path):
    """(SimConfig, VirtualFace) of a simulated session (its truth/truth.json next to session/),
    or None for a real one. ``path``: the session folder, its parent, or a `mocap run` output."""
    from mocap.simulate import preset
    from mocap.simulate.effects import CombinedEffect, HiddenEffect, make_effect
    from mocap.simulate.session_writer import virtual_rig_and_face

    p = Path(path)
    if (p / "summary.json").is_file():
        sdir = json.loads((p / "summary.json").read_text()).get("session", {}).get("dir", "")
        p = Path(sdir) if sdir else p
    for cand in (p / "truth" / "truth.json", p.parent / "truth" / "truth.json"):
        if cand.is_file():
            info = json.loads(cand.read_text())
            c = info["config"]
            eff = info.get("effect", {})
            parts = eff["effects"] if "effects" in eff else [eff]
            names = [e.get("name", "none") for e in parts]
            strengths = [e.get("strength", 0.0) for e in parts]
            forms = {e.get("form", "model") for e in parts}
            if len(forms) > 1:
                effect = CombinedEffect(tuple(HiddenEffect.default(n, s, e.get("form", "model"))
                                              for n, s, e in zip(names, strengths, parts)))
            else:
                effect = make_effect(names, strengths if names != ["none"] else None,
                                     form=forms.pop())
            # the family the session was made with (the one drawn for 'random'), so the closed
            # loop plays the same face as the session's takes
            family = info.get("face_family", {}).get("name", c.get("face_family", "pi"))
            cfg = preset(c["preset"], seed=c["seed"], du_ids=tuple(c["du_ids"]),
                         n_markers=c["n_markers"], n_trials=c["n_trials"],
                         n_cameras=c.get("n_cameras"), fps=c["fps"], effect=effect,
                         face_family=family)
            return cfg, virtual_rig_and_face(cfg)[2]
    return None


def play_virtual(cfg, face, rows: pd.DataFrame, duration_s: float, noise_mm: float = 0.0,
                 seed: int = 0, trial_variation: bool = True) -> np.ndarray:
    """Marker positions (n_frames, M, 3) mm of ``rows`` played on the virtual face with its hidden
    effect: noise-free (the mean response), or with ``noise_mm`` of measurement noise and, with
    ``trial_variation``, a real take's trial-to-trial variation (see :func:`play_virtual_take`)."""
    return play_virtual_take(cfg, face, rows, duration_s, noise_mm, seed, trial_variation)[1]


def play_virtual_take(cfg, face, rows: pd.DataFrame, duration_s: float, noise_mm: float = 0.0,
                      seed: int = 0, trial_variation: bool = True) -> tuple[np.ndarray, np.ndarray]:
    """A take of ``rows`` on the virtual face: (true, measured) marker positions (n_frames, M, 3)
    mm. Noise-free (``noise_mm`` 0) both are the face's mean response; otherwise the measured
    positions add ``noise_mm`` of measurement noise per axis to the true ones, which (with
    ``trial_variation``) carry a real take's trial-to-trial variation: bias and amplitude shifts,
    the family's per-take bias shift and the skin's jitter, drawn from ``seed``. Score a design
    on the true positions: the evaluation's normalised displacement is biased by noise."""
    from mocap.simulate.motion import true_positions

    n = int(round(duration_s * cfg.fps))
    rng = np.random.default_rng(seed) if noise_mm > 0 else None
    X = true_positions(face, cfg.effect, rows, n, cfg.fps, 1, rng if trial_variation else None)
    if rng is None:
        return X, X
    return X, X + rng.normal(0.0, noise_mm, X.shape)
