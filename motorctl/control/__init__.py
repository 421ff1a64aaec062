"""The controllers: DCDIARC (C1 and C2 as two configurations of one class), its projection-type
least-squares estimator and the cubic input inversion (Chen, Yao & Wang 2013)."""
