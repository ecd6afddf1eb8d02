"""Every sample on disk: the MCAP writer that never makes the loop wait (`writer`), the
reader and crash recovery (`reader`), rotation and log faults (`rotate`), and import of
other systems' CSV recordings (`import_csv`). Owns [log] config.

May import: the root vocabulary only (records, errors, rt). Never loop, daemon, analysis
or cli: a log is data, whoever wrote it."""
