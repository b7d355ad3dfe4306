"""The applications on top of the areas: the `earcore` command (`cli`), the main job
(`run`), the quick map demo (`demo`), the rerun recording, calibration in the
simulated cell (`calibrate`) and the papers' experiments (`experiments`)."""
