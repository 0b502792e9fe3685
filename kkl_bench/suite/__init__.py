"""How a task is defined: tracks and their files, tasks, profiles and pinned test sets,
and the plants that make a task's data.

Layer: imports the protocol, the measurement model and the registry."""
