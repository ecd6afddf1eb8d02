"""The paper's procedures as computations: inverted-pendulum design (`design_ip`), torsion
stiffness and compliance (`stiffness`), centre-of-mass calibration (`calibrate_com`) and
the two-stage pendulum (`two_stage`).

May import: the root vocabulary, `leveler.sim`, analysis. Never daemon, emulate or cli."""
