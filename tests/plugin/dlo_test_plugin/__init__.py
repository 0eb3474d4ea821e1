"""A dlocli plugin as a third party would write one: a dynamics model, a backend, a learning
agent and a planner, each one module, each registered by one entry-point line
(``dlo_test_plugin-0.1.dist-info/entry_points.txt``). The tests put this folder on the path
of a fresh process, where dlocli finds it as an installed package."""
