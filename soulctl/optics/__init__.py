"""Optical models: photometry now; pupil, ASM modes, atmosphere, PWFS and detector to come."""
