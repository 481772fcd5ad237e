"""Evaluation: the metrics (FGD, beat alignment, diversity...), the evaluation command, the quality suite and the
realism report. Nothing below `gesture.eval` imports it."""
