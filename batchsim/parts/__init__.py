"""The parts a system is made of beside its engine (batchsim.hardware), each built with what it
needs: readings.py (what read() fills, its views, the frozen rule), actuation.py and
transmissions.py (commands -> ctrl beyond a copy), sensing.py (cameras, lidars, noise), poses.py
(every body's pose), failures.py (failed worlds said once each), and face.py (what every system
shows a user over its parts, BatchedSystem and a fleet over devices alike).
"""
