"""Tests of ar_anchor/cli/."""
