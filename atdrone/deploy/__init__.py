"""Flying a population member on Crazyflie drones: the deploy layer (beside the service).

Modules, each importing only from those above it and from the layers below deploy:

- ``clock``: real time, or a scaled clock that runs the simulated fleet faster than real time.
- ``shield``: the safety shield, pure functions on arrays (geofence, separation, clamps,
  stale poses, stalls, link loss, battery, stop requests).
- ``crtp``: the CRTP packet formats the bridge and the simulated fleet both speak.
- ``simfleet``: simulated Crazyflies answering cflib on loopback UDP ports, with dynamics,
  the firmware's watchdogs and injectable faults.
- ``mocap``: motion-capture sources (the ``motioncapture`` package, or a simulated one
  reading the fleet) read in their own thread, and the mocap-to-arena frame transform.
- ``bridge``: the bridge protocol and its cflib implementation (Swarm + CachedCfFactory).
- ``config``: the deploy document (configs/deploy/*.json), validated.
- ``flightlog``: per tick and drone rows, Parquet, the MLflow deploy run, the summary;
  ``flightplot``: its pictures.
- ``preflight``: the dry run's checks (tracking, spawn regions, batteries, the frame,
  the observation agreement with ``BatchedPursuit``, the command path).
- ``links``: link health (a paused host told from a lost drone); ``reactions``: one severity
  order for fault reactions.
- ``simdrone`` (one drone's firmware model), ``simradio`` (the Crazyradio model),
  ``simproc`` (the fleet in a process of its own).
- ``loop``: the 10 Hz loop (``Flight``), made of ``episode`` (one episode), ``sequence``
  (spawn draws and transits between episodes), ``landing`` (landing, reactions,
  confirmation, how each drone ended) and ``backup`` (a partner drone dropped alone, a
  backup drone taking its slot); ``team`` and ``faults`` beside it; ``job``: the whole
  deploy job, ``gap``: its comparison with the training simulator.

cflib and motioncapture are the optional extra ``atdrone[deploy]``: nothing outside this
package imports them, and this package imports them only where it talks to hardware.
"""
