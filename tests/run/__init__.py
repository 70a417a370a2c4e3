"""Tests of ar_anchor/run/."""
