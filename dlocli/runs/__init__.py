"""The runs behind the commands, one module each holding its ``run_…()``: goal, collect,
train, evaluate (`dlo eval`), calibrate, control, online (the paper's Algorithm 1) and
export. The CLI (:mod:`dlocli.cli`) parses flags, builds the spec, calls one and prints."""
