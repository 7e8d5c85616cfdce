"""The training graph's wire protocol, without ROS or DDS: topics and message layouts
(:mod:`.wire`), following the environment's steps by key (:mod:`.follower`), and joining
a group's messages into replay episodes (:mod:`.assembly`; for the learner node's
subscriptions, with its credit, :mod:`.group`). Nodes and bags share it."""
