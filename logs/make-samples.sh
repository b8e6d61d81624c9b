#!/bin/sh
# Regenerates the sample logs in this directory (see README.md). Run from the repository root:
#     sh logs/make-samples.sh
# The scans are simulated, so the logs are reproducible bit for bit except for their
# provenance (git commit, host, creation time) and wall-clock timing channel.
set -eu
cd "$(dirname "$0")"
rm -f pallet-320x240.mcap pallet-320x240.mcap.outcomes.jsonl mixed-640x480.mcap
rm -rf ros2-pallet-320x240
boxloc run "sim:pallet:width=320,height=240,f=262.5" --count 2 --seed 1 \
    --record pallet-320x240.mcap --quiet
boxloc annotate pallet-320x240.mcap --scan 0 --surface 0 --pick ok
boxloc annotate pallet-320x240.mcap --scan 1 --surface 0 --pick failed \
    --reason "suction lost the box on lift-off"
boxloc run "sim:mixed" --seed 4 --record mixed-640x480.mcap --quiet
# the same two pallet scans as a ROS 2 bag (a depth camera's recording), for `boxloc run BAG`
"${PYTHON:-python3}" make-ros2-sample.py
du -b ./*.mcap ./*.jsonl ros2-pallet-320x240
