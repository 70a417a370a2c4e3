"""Tests of ar_anchor/viz/."""
