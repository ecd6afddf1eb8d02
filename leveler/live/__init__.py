"""Optional servers that show the running loop to the lab: the Foxglove live stream and
EPICS Channel Access PVs.

Owns its config tables ([live], [epics]) and the servers. May import the kit, the log (the
topics and schemas it publishes as the log writes them) and analysis (the running spectrum);
the loop hands the stream records as to any sink. Neither controls anything of itself: an EPICS put
is handed to the daemon's own request path, with its checks.
"""
