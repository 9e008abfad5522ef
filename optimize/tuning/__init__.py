"""Tuning gains by gradient through whole rollouts: parameters, cost, batches, methods, the loop, the job."""
