"""Device emulators: the simulated plant behind the real protocols, Modbus TCP/RTU (`modbus`)
and serial on ptys (`serial`), with timed fault injection (`faults`), so the real drivers
are tested against real wire traffic.

May import: the root vocabulary, `leveler.sim`, `leveler.drivers`' configs. Never daemon,
analysis or cli."""
