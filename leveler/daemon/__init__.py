"""The service around the loop: the daemon on a real-time clock (`service`), the control
socket (`control_server`, `protocol`, and the `client` the CLI uses), sd_notify (`notify`),
tuning written back to the config (`persist`) and `make install` (`install`). Owns
[control] config.

May import: the root vocabulary, settings and stand, loop, log, and analysis for the
stability check of new gains. Never cli, procedures or emulate."""
