"""Offline commissioning tools (DESIGN §2, §15): the single-actuator rig and its sampled-loop
analysis, workspace analysis, lock-step runs, tracking figures and scenarios.  Depends on
cdpr, drivers and sim_bus; used by the command line and bench/."""
