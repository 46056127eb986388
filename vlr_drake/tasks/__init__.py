"""The paper's three manipulation tasks with the Jacobian controller (its Fig. 6A, 6B and 7).

- :func:`vlr_drake.tasks.write.run_write`: handwriting, position control only.
- :func:`vlr_drake.tasks.maze.run_maze`: marble maze, orientation control only.
- :func:`vlr_drake.tasks.stack.run_stack`: cup stacking, SE(3) control with alpha = 9.5.

Each returns the task result dict of docs/result-files.md and writes its plots to ``out``.
"""
