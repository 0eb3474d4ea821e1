"""`dlo bench`: the spec and schedule, the agents, the jobs, where they run, and the report."""
