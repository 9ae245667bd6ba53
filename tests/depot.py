"""The fleet of groups the groups' ROS, recording and view tests share: two worlds of an arm
alone, and two of an arm beside a rover."""

DEPOT = {
    "groups": [
        {"name": "arms", "worlds": 2, "robots": [{"name": "arm", "model": "arm"}]},
        {
            "name": "yard",
            "worlds": 2,
            "robots": [{"name": "arm", "model": "arm"}, {"name": "rover", "model": "rover", "pose": [0.0, 2.0, 0.0, 0.0]}],
        },
    ]
}
