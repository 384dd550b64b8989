"""A simulated fleet: robots that drive a building and put what real robots would put.

One generator serves ``rlutf simulate``, ``rlutf demo``, the benchmarks and the tests:

* :mod:`service.sim.plan` (pure) draws the plan from a seed: the building, each robot's path,
  its drifting odometry and a noisy scan at each pose, the initial poses, and the optional
  schedules of Relocalize requests and bad inputs.
* :mod:`service.sim.wire` turns the plan into payloads: the JSON robots of WIRE.md or ROS 2
  robots (CDR on rmw_zenoh's keys), stamped as they are sent.
* :mod:`service.sim.fleet` puts them on Zenoh at the robots' rate, in time order.
* :mod:`service.sim.demo` is ``rlutf demo``: a service and this fleet, shown live.

The part sits above :mod:`service.live` (it is a client of the service, as the CLI is): it may
import ``keys``, ``config``, ``maps``, ``logs``, ``live`` and ``ros2``; nothing but ``cli``
imports it.
"""
