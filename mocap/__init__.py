"""facemocap: facial motion capture from raw multi-camera exports to a quantitative face model.

The Python API (:mod:`mocap.api`)::

    import mocap

    result = mocap.run(mocap.load_session("sample_data/session"))   # writes nothing
    result.properties, result.trajectories, result.arrays["rest"]

``mocap.load_session``, ``mocap.calibrate``, ``mocap.reconstruct``, ``mocap.analyze`` and
``mocap.run`` are imported on first use, so ``import mocap`` stays light (it imports neither
rerun, matplotlib nor dask; nor do these functions unless a run writes its figures or recording).

Subpackages, one layer each (imports go one way, down this list): ``mocap.core`` (session
types, manifest, readers), ``mocap.calib`` (camera models, wand calibration), ``mocap.simulate``
(the virtual face and rig), ``mocap.reconstruction`` (correspondence, labeling, trials) and
``mocap.interop`` (vendors' files), ``mocap.analysis`` (the paper's analyses, the face model),
``mocap.workflows`` (run, audit, discrepancy, design), ``mocap.outputs`` (figures, Rerun),
``mocap.cli``.

Units everywhere: millimetres (mm), pixels (px), seconds (s), command units (integers 0..255).
"""

__version__ = "0.1.0"

__all__ = ["load_session", "calibrate", "reconstruct", "analyze", "run", "RunSettings"]


def __getattr__(name: str):
    if name in ("load_session", "calibrate", "reconstruct", "analyze", "run"):
        from mocap import api

        return getattr(api, name)
    if name == "RunSettings":
        from mocap.workflows.run.settings import RunSettings

        return RunSettings
    raise AttributeError(f"module 'mocap' has no attribute {name!r}")


def __dir__():
    # the API, the version and the subpackages already imported; not this file's helpers
    public = {n for n in globals() if not n.startswith("_")}
    return sorted(public | set(__all__) | {"__version__"})
