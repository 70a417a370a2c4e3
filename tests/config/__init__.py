"""Tests of ar_anchor/config/ and the camera file."""
