"""The package object of ``mocap``: ``mocap.reconstruct`` is both the reconstruction subpackage
(``mocap.reconstruct.labeling`` ...) and the Python API's stage function
(:func:`mocap.api.reconstruct`), so ``mocap.reconstruct(session, calibration)`` works as the API
promises while ``import mocap.reconstruct.labeling`` and ``mock.patch`` keep working.
"""

import types


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

