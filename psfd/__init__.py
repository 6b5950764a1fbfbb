"""psfd: unattended sub-pixel camera PSF measurement.

Data flows one way: plan -> runner -> drivers -> RAW files -> estimator -> catalogue.
The modules, from the bottom up (each imports only those above it in this list):

- ``errors``: the typed errors a user can cause, each with its exit code (the README's one table).
- ``vocabulary``: the names and sizes every part shares: methods (``bernoulli``,
  ``two-photo``, ``sharp-edge``) and their older aliases, solvers and the default
  solver, channels, rail axes, f-numbers, the default ``s`` per method, and the one
  check of each size a user gives with its bound (``s``, ``support``, ``grid``, image
  pixels, workers, backlog, plan steps and bytes, control-socket requests).
- ``workers``: forked worker processes: the cores this process may use, the signal set-up of a worker.
- ``exif``: a frame's metadata read from the RAW file itself (focal length, f-number,
  exposure, ISO, lens, serial, pixel pitch) and the check of requested against actual settings.
- ``estimator/``: pure numerics, arrays in and arrays out, one module per step of the papers:
  ``raw`` (frames and Bayer planes), ``target`` (the printed pattern's layout), ``detect``
  (finding the target), ``geometry`` (the target's maps: homography, radial distortion,
  thin-plate spline), ``radiometry`` (illumination and response curve), ``resample``
  (DCT band-limiting, Keys interpolation), ``bernoulli`` (the noise-target method),
  ``pair_register`` (near/far pair registration), ``twoscale`` (the two-photo method),
  ``fourier`` (the orthonormal DCT/DST and FFT convolution on OpenCV's DFT, without scipy's
  start-up), ``quantiles`` (numpy's median and percentiles without numpy.ma's import),
  ``nnls`` (non-negative least squares on the normal equations, the Bernoulli and sharp-edge solves),
  ``sharpedge`` (the sharp-edge baseline), ``kernels`` (the PSF record and kernel
  conventions), ``mtf`` (MTF profiles, MTF50, FWHM, errors between kernels), ``gamma``
  (conditioning of a pattern), ``simulate`` (rendering frames of known PSF).
- ``drivers/``: the ``Camera`` and ``Rail`` protocols (``base``), libgphoto2 (``gphoto``),
  GRBL (``grbl``) and the process that stops its carriage when psfd is killed mid-move
  (``grbl_guard``, standard library only), the simulated rig (``sim``) and recordings (``recording``).
- ``printing``: the calibration targets rendered for print.
- ``figures``: every picture psfd draws (PSF figure, array images, method comparison, field report),
  with matplotlib, loaded only by the commands that draw.
- ``catalogue``: the SQLite catalogue; all SQL, and the rule of which run of a plan is unfinished.
- ``daemon/``: plans (``plan``), estimation jobs in worker processes (``work``), the
  content-addressed frame store (``store``), the resumable runner and ``run_plan``
  (``runner``), the control-socket client (``client``) and the service (``service``).
- ``cli/``: the ``psfd`` command line, thin: option values and shared option groups
  (``options``), what commands write and print (``output``: files, CSV, JSON, tables with units),
  where the log goes (``logs``: -v/-q, stderr, journald), and one module per group of
  commands (``target``, ``estimate``, ``compare``, ``hardware``, ``query``, ``lab``).
"""

__version__ = "0.1.0"
