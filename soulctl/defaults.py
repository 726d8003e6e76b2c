"""The one home of the defaults of a simulated run: what `loop run`, `optimize gains`, `sweep`
and the Python API assume when the user says nothing.  The run description
(``soulctl.run_config``) takes its field defaults from here; `soulctl loop run --print-config`
prints them resolved.  Physical constants of the telescope and the tables' values have their
own homes (``optics.pupil``, ``tables/``); these are choices of a run."""

MAGNITUDE_R = 9.7  # the paper's bright-star on-sky tests (Sec. 4)
SEEING_ARCSEC = 1.0  # at 500 nm, on the line of sight
WIND_M_S = 8.0  # effective wind speed of the LBT profile
L0_M = 25.0  # outer scale
DURATION_S = 0.2  # simulated time of `loop run`
BAND = "H"  # science band of the Strehl ratio
SEED = 1
OVERSAMPLING = 2  # simulation pixels per binning-1 detector pixel
# The pyramid's simulated field of view (a diameter, arcsec; 0: the field the pupil's sampling
# gives, +-0.75" at oversampling 2, with no stop): SOUL's.  The sampled field read partly
# corrected residuals 30-40 % low at 1.5" and let the pupil's rim lock falsely (docs/physics.md,
# "The pyramid's field of view"); SOUL's costs ~2x a loop frame (bench/bench_frame_cost.py).
SOUL_FIELD_OF_VIEW_ARCSEC = 2.1  # SOUL's WFS field, a diameter (Arcetri error budget; LBTO elab_lib)
WFS_FIELD_ARCSEC = SOUL_FIELD_OF_VIEW_ARCSEC
# What a description or telemetry soulctl stored without ``wfs_field_arcsec`` ran: the key was
# written only when set until SOUL's field became the default, so such a file re-runs with 0.
PREDATED_WFS_FIELD_ARCSEC = 0.0
# The science path's NCPA: the paper's LUCI1 carried ~100 nm (Sec. 3.1 and the caption of the
# Tip/Tilt results table), compensated on sky by reference-slope offsets once OGTL has
# calibrated k (Sec. 2.4, Modal Gain Machine).
NCPA_RMS_NM = 100.0
# The fraction of the NCPA's offsets the RTC applies (``optics.ncpa``): in full, the R10.9
# on-sky-like loop (1212 Hz, 40x40, 1.0", 13 m/s) folded into a false lock of the pyramid in
# 3 of 4 seeds within 10 s; at half, none did, and half wins back 3/4 of the NCPA's variance
# on the controlled modes (docs/physics.md, "Non-common-path aberrations").
NCPA_OFFSET_FRACTION = 0.5
MEASURE_S = 0.5  # `optimize gains`: before and after
# `optimize gains`'s paired evaluation: before and after each measured over this many
# consecutive windows of MEASURE_S; their mean and the standard error of the paired difference
# are the result (one window's difference moved by 0.02-0.04 from one 1 s window to the next at
# R17.5-18.5, 0.6": docs/physics.md)
EVALUATION_WINDOWS = 4
