"""Tests of ar_anchor/track/."""
