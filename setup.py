"""Setuptools entry point; metadata lives in setup.cfg (ament_python convention)."""

from setuptools import setup

setup()
