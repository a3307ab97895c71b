"""Synthetic data sets: the corridor RGB-D sequence and the household room."""
