"""The shared-memory protocols between the loop's process and the bridge workers (and the
recorder and view processes); no rclpy. Each protocol's arrays, writer and reader are in one
module; nothing outside this package indexes their arrays.

    snapshot.py   what the loop publishes each control period: a ring of seqlocked headers
                  (status, flags) and each channel's last rows
    demand.py     which channels someone reads (a worker, a recording, the view)
    commands.py   commands from the workers to the loop: per-world command slots, and each
                  side's rejections
    requests.py   what a worker hands the loop through its ring: trajectory batches and
                  service requests, encoded and decoded
    services.py   the loop's answers to a worker's requests
    goals.py      action goals the loop refused, and why (Refusal)
    active.py     which controllers are active in each world
    liveness.py   each worker's tick counter, and the workers that stopped ticking
    sensor_blocks.py  cameras' images and lidars' scans per world, seqlocked per world; the
                  workers' want bits and the view's camera request
    recording.py  the periods queued for the recorder, whether a recording runs, its mailbox
    world_params.py  each randomized world's draw, as a line for /diagnostics
    text.py       text in NUL-padded byte rows

The arrays themselves are batchsim.memory's (named arrays and byte rings in shared memory).
"""
