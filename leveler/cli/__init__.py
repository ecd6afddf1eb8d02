"""The `leveler` command: `main` holds the table of commands; each command (or family of
control-socket verbs) is one module here that owns its parser and its `run(args)`.

The only wing that may import every other; nothing imports it."""
