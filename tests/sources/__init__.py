"""Tests of ar_anchor/sources/."""
