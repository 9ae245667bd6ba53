"""Calibration against a real robot (`batchsim calibrate`): a rosbag2 MCAP of the robot's joint
states and the commands its controllers received is replayed into N worlds that differ by a
`randomize:` block's draws, and the ranges are narrowed round by round toward the draws whose
joint states track the real ones best.

- bag.py: the real bag read and checked (joint states per joint over time, the commands);
- parameters.py: the search's parameters, one per varied object, and a round's Variation;
- the batched search itself (cross-entropy over a box, pure NumPy, seeded) is batchsim.variation.search,
  beside the draws it narrows;
- replay.py: the bag's commands into N worlds in lockstep, each world's error per joint;
- fit.py: the rounds: search, replay, narrow; the fit before and after;
- report.py: the table, JSON, plot and the fitted randomize block;
- synthetic.py: a "real" bag made by batchsim with hidden parameter changes (tests, benchmark).
"""

from batchsim.calibration.bag import BagError, Command, RealBag, read_bag
from batchsim.calibration.fit import Fit, FitOptions, calibrate
from batchsim.variation.search import BoxSearch

__all__ = ["BagError", "BoxSearch", "Command", "Fit", "FitOptions", "RealBag", "calibrate", "read_bag"]
