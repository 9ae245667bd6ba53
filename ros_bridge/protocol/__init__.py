"""The shared-memory protocol between the loop's process and the bridge workers; no rclpy.

    snapshot.py   what the loop publishes each control period: two seqlocked buffers of
                  status, flags and the channels some worker wants (writer and reader)
    commands.py   commands from the workers to the loop: per-world command slots and the
                  loop's rejection marks (writer and reader)
    requests.py   what a worker hands the loop through its ring: trajectory batches and
                  service requests, encoded and decoded
    sensor_blocks.py  cameras' images and lidars' scans per world, seqlocked per world
                  (writer and reader), and the workers' want bits

The arrays themselves are batchsim.memory's (named arrays and byte rings in shared memory).
"""
