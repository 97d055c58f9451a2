"""World alignment SLAM → ECEF: offline rough (TerraSLAM §4.3), online fine (§4.4), GNSS bootstrap."""
