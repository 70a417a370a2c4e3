"""Tests of ar_anchor/synthetic/."""
