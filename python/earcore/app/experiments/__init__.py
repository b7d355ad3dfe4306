"""The papers' experiments in the simulated cell: Paper II's Table II and Fig. 7
(`planning`), Paper I's Tables II-III (`calibration`)."""
