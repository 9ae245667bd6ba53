"""The packages of the wheel, found: pyproject.toml says the rest.

Every folder with an __init__.py under batchsim/ and ros_bridge/ (a package listed by hand was
left out of the wheel: issue 42), and batchsim.models, which lives in models/ (pyproject's
package-dir): setuptools' find in pyproject.toml names packages only by their folders.
"""

from setuptools import find_packages, setup

setup(packages=[*find_packages(include=["batchsim*", "ros_bridge*"]), "batchsim.models"])
