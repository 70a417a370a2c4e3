"""Tests of ar_anchor/bench/."""
