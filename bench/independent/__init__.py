"""An independent test-data generator for `leveler diagnose` (bench/diagnose_score.py).

Written only from the physics brief, the paper and the documented log format: it shares no
code and no model form with the simulator or the detector it is meant to judge.
"""
