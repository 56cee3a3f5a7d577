"""Interoperability with vendors' software: C3D in and out, OptiTrack Motive CSV, Qualisys QTM
TSV and Vicon Nexus CSV in. Every reader returns a :class:`MarkerData` and a list of notes (the
documented repairs it made); errors name the file and the place.
"""

from mocap.interop.marker_data import ImportError_, MarkerData

__all__ = ["ImportError_", "MarkerData"]
