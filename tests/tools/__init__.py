"""Tests of ar_anchor/tools/."""
