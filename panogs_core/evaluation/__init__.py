"""Scoring a run: the metrics (mIoU, mAcc, PRQ) and the simplest baselines every table keeps beside the method."""
