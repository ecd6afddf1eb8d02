"""The paper's procedures as computations: inverted-pendulum design (`design_ip`), torsion
stiffness and compliance (`stiffness`), centre-of-mass calibration (`calibrate_com`),
the two-stage pendulum (`two_stage`) and tilt modulation analysis (`tilt_modulation`).

May import: the root vocabulary, settings, `leveler.sim`, loop (the wave's shape), analysis.
Never daemon, emulate or cli."""
