"""The runs behind the commands that write a run directory: collect, control and online
(the paper's Algorithm 1)."""
