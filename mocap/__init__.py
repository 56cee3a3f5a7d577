"""facemocap: facial motion capture from raw multi-camera exports to a quantitative face model.

The Python API (:mod:`mocap.api`)::

    import mocap

    result = mocap.run(mocap.load_session("sample_data/session"))   # writes nothing
    result.properties, result.trajectories, result.arrays["rest"]

``mocap.load_session``, ``mocap.calibrate``, ``mocap.reconstruct``, ``mocap.analyze`` and
``mocap.run`` are imported on first use, so ``import mocap`` stays light (it imports neither
rerun, matplotlib nor dask; nor do these functions unless a run writes its figures or recording).

Subpackages: ``mocap.calib`` (camera models, wand calibration), ``mocap.reconstruct``
(correspondence, labeling, trials), ``mocap.analysis`` (the paper's analyses, the face model),
``mocap.simulate`` (the virtual face and rig), ``mocap.interop`` (vendors' files).

Units everywhere: millimetres (mm), pixels (px), seconds (s), command units (integers 0..255).
"""

import sys
import types

__version__ = "0.1.0"

__all__ = ["load_session", "calibrate", "reconstruct", "analyze", "run", "RunSettings"]


def __getattr__(name: str):
    if name == "reconstruct":  # the subpackage, callable (see _ReconstructPackage)
        import mocap.reconstruct

        return mocap.reconstruct
    if name in ("load_session", "calibrate", "analyze", "run"):
        from mocap import api

        return getattr(api, name)
    if name == "RunSettings":
        from mocap.run_settings import RunSettings

        return RunSettings
    raise AttributeError(f"module 'mocap' has no attribute {name!r}")


def __dir__():
    return sorted(list(globals()) + __all__)


class _ReconstructPackage(types.ModuleType):
    """``mocap.reconstruct`` is both the reconstruction subpackage (``mocap.reconstruct.labeling``
    ...) and the API's stage function: calling the package runs :func:`mocap.api.reconstruct`."""

    def __call__(self, session, calibration=None, **kwargs):
        from mocap import api

        return api.reconstruct(session, calibration, **kwargs)


class _Package(types.ModuleType):
    def __setattr__(self, name: str, value) -> None:
        # the import system binds the subpackage here when it is first imported
        if name == "reconstruct" and isinstance(value, types.ModuleType):
            value.__class__ = _ReconstructPackage
        super().__setattr__(name, value)


sys.modules[__name__].__class__ = _Package
