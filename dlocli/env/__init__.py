"""The shape-control task: the Gymnasium env, its tasks, start and goal shapes, metrics and
the one episode loop."""
