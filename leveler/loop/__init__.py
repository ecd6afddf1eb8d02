"""The control cycle: read -> update -> write -> log with time passed in (`cycle`), the PID
(`pid`), the clocks that pace it, real or virtual (`clock`), and the square wave it can drive
(`modulation`). Owns [loop] and [controller] config.

May import: the root vocabulary (errors, records, typed_config, rt) and `leveler.drivers`'
protocols. Never log, daemon, analysis, procedures, emulate or cli: the loop must run the
same in the daemon, the simulator and every test."""
