"""Optional servers that show the running loop to the lab: the Foxglove live stream.

Owns its config table ([live]) and the servers. May import the kit, the log (the topics and
schemas it publishes as the log writes them) and analysis (the running spectrum); the loop
hands it records as to any sink, and it never controls anything.
"""
