"""The procedures the CLI and the nodes both drive.

Batch (``lidarcal calibrate``, ``lidarcal correct``) and streaming (the nodes) call the same
functions here, which call :mod:`lidarcal_ros.core` for numerics and :mod:`lidarcal_ros.io` for
data, so the two cannot drift apart.

Modules: :mod:`.calibration` (load a mission, calibrate, report, simulate to files),
:mod:`.correction` (apply a calibration and the radiometric model to clouds).
"""
