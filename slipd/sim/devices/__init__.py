"""Emulated devices for the simulated rig and the tests: each speaks its real wire protocol.

``papillarray.EmulatedPapillArray`` streams PTSCOM 2.0 frames on a pty. Import the device modules
directly; this package imports nothing so that loading one emulator never pulls in the others.
"""
