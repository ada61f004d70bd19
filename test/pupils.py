"""Sensors the tests share (not collected: no tests here)."""

from lgs_wfs_ros.sensor import Sensor

#: the full pupil's radii (0.3-15 m from the centre, so its elongations and the spots its
#: field cuts) on a 30 x 30 pupil of 1 m subapertures: a quarter of its 2,784 blocks, and of
#: the thin-layer basis every calibrated estimator builds (15 s for the full cartesian pupil)
SMALL = Sensor(n_subaps=30, subap_pitch_m=1.0)
