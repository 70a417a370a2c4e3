"""Tests of ar_anchor/render/."""
