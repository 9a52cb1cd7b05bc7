"""Presentation shared by every command: colour conventions, figure panels, PNG writing.

A leaf package like :mod:`protocol`: it imports only numpy, OpenCV and
matplotlib, so ``flight_sw``'s command line, the HIL run report and the studies
can all draw with one convention.
"""
