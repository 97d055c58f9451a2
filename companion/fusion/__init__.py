"""The fusion's parts, each a measurement the pipeline (companion.pipeline.Localizer) takes or a
source of a fix's σ; the Localizer wires them per frame:

  gnss_fit.py      GNSS pairs and the similarity fitted to them (digital-twin §III-D)
  registration.py  GIS registrations of the SLAM map in a worker process (TerraSLAM §4.4)
  barometer.py     the barometer's offset to ellipsoidal height, learned from GNSS
  follow.py        alignments carried along when local mapping moves their points
  integrity.py     GNSS against visual odometry, SLAM speed against GNSS speed, the GNSS fits' walk
  sigma.py         where σ comes from: an alignment's σ at a camera, widening, walk and denial floors
"""
