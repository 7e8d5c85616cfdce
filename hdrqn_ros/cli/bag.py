"""``hdrqn bag``: inspect (info), repair and play rosbag2 (MCAP) bags."""
from __future__ import annotations

import json
import os
import sys

from hdrqn_ros.cli.common import UsageError


def add_bag(sub) -> None:
    parser = sub.add_parser("bag", help="inspect and repair rosbag2 (MCAP) bags",
                            description="rosbag2 bags with MCAP storage (what ros2 bag record -s mcap writes).")
    bag_sub = parser.add_subparsers(dest="bag_command", metavar="BAG_COMMAND", required=True)
    info = bag_sub.add_parser("info", help="topics, types, message counts, time span and files of a bag")
    info.add_argument("bag", metavar="BAG_DIR")
    info.add_argument("--json", action="store_true", help="print JSON")
    repair = bag_sub.add_parser("repair", help="recover a bag whose recorder was killed (complete chunks are kept)")
    repair.add_argument("bag", metavar="BAG_DIR")
    play = bag_sub.add_parser(
        "play", help="publish a bag's messages on their recorded topics, paced by their timestamps (ros2 bag play)",
        description="Runs the player node (hdrqn_ros/nodes/player.py) in this process: each message goes out on its "
                    "recorded topic with the recorded QoS, /clock carries the bag time. The node runs on rclpy "
                    "(ROS 2 Jazzy: the 'ros' extra on Linux x86-64); DDS stays on the loopback "
                    "interface unless --interface is given. Put --topics after the bag directories.")
    play.add_argument("bags", nargs="+", metavar="BAG_DIR", help="bag directories, played together in timestamp order")
    play.add_argument("--rate", type=float, default=1.0, help="playback speed: bag seconds per second (default 1.0)")
    play.add_argument("--loop", action="store_true", help="start over at the end, until Ctrl-C")
    play.add_argument("--topics", nargs="+", default=[], metavar="T", help="play only these topics (default: all)")
    play.add_argument("--no-clock", action="store_true", help="do not publish /clock")
    play.add_argument("--delay", type=float, default=1.0,
                      help="seconds between creating the publishers and the first message, for DDS discovery (default 1.0)")
    play.add_argument("--wait-for-subscribers", type=int, default=0, metavar="N",
                      help="before playing, wait until every topic has at least N subscribers (default 0: no wait)")
    play.add_argument("--domain-id", type=int, help="ROS_DOMAIN_ID (default: $ROS_DOMAIN_ID or 0)")
    play.add_argument("--interface", help="network interface for DDS (default: loopback only)")


def _bag_play(args) -> int:
    """``hdrqn bag play``: the player node in this process."""
    import math

    from hdrqn_ros.dds import INTERFACE_ENV
    from hdrqn_ros.nodes.ros_packages import RosNotInstalled, require_rclpy

    if not (math.isfinite(args.rate) and args.rate > 0):
        raise UsageError(f"--rate must be > 0, got {args.rate}")
    if not (math.isfinite(args.delay) and args.delay >= 0):
        raise UsageError(f"--delay must be >= 0, got {args.delay}")
    if args.wait_for_subscribers < 0:
        raise UsageError(f"--wait-for-subscribers must be >= 0, got {args.wait_for_subscribers}")
    if args.domain_id is not None:
        if not 0 <= args.domain_id <= 232:
            raise UsageError(f"--domain-id must be in 0..232, got {args.domain_id}")
        os.environ["ROS_DOMAIN_ID"] = str(args.domain_id)

    # the player's parameters, as values (the same names as its --ros-args -p ones under ros2 run)
    parameters = {"bag": list(args.bags), "rate": float(args.rate), "loop": bool(args.loop),
                  "topics": list(args.topics) or [""], "clock": not args.no_clock, "delay": float(args.delay),
                  "wait_for_subscribers": int(args.wait_for_subscribers)}
    if args.interface:  # a process setting, like ROS_DOMAIN_ID
        os.environ[INTERFACE_ENV] = args.interface
    try:
        require_rclpy()
    except RosNotInstalled as exc:
        raise UsageError(str(exc)) from None

    def progress(player) -> None:
        if player.bag_time_ns is None or player.start_ns is None:
            return
        done = max(0, player.published - (player.passes - 1) * player.total)
        print(f"bag play: pass {player.passes}, {done}/{player.total} messages, bag time "
              f"{(player.bag_time_ns - player.start_ns) / 1e9:.2f}/{(player.end_ns - player.start_ns) / 1e9:.2f} s",
              file=sys.stderr, flush=True)

    from hdrqn_ros.nodes.player import PlayerNode, parameter_overrides  # both import rclpy: after require_rclpy()
    from hdrqn_ros.nodes.process import run_node

    return run_node(lambda **kw: PlayerNode(progress=progress, parameter_overrides=parameter_overrides(parameters),
                                            **kw), ["hdrqn bag play"])


def cmd_bag(args) -> int:
    from hdrqn_ros.recording.bag import BagError, bag_summary, repair_bag
    from hdrqn_ros.recording.transitions import episode_summary

    if args.bag_command == "play":
        return _bag_play(args)
    try:
        if args.bag_command == "repair":
            report = repair_bag(args.bag)
            print(f"{report.path}: {report.message_count} messages in {len(report.files)} file(s); repaired "
                  f"{len(report.repaired)} file(s), recovering {report.messages_recovered} messages and dropping "
                  f"{report.bytes_dropped} bytes of incomplete data")
            return 0
        summary = bag_summary(args.bag)
    except BagError as exc:
        raise UsageError(str(exc)) from None
    try:
        summary["episodes"] = episode_summary(args.bag)
    except BagError as exc:  # env_step topics of another layout: the rest of the summary still holds
        summary["episodes"], summary["episodes_error"] = {}, str(exc)
    if args.json:
        print(json.dumps(summary, indent=2))
        return 0
    print(f"bag:      {summary['path']}\nfiles:    {len(summary['files'])}\nmessages: {summary['message_count']}\n"
          f"duration: {summary['duration_s']:.3f} s")
    width = max((len(t) for t in summary["topics"]), default=5)
    for topic, entry in sorted(summary["topics"].items()):
        print(f"  {topic:{width}s}  {entry['count']:8d}  {entry['type']}")
    groups = summary["episodes"]
    if "episodes_error" in summary:
        print(f"episodes: not readable as hdrqn transitions ({summary['episodes_error']})")
    if groups:
        print("episodes (complete; mean return, success rate, mean steps; incomplete):")
        width = max(len(g) for g in groups)
        for group, group_stats in sorted(groups.items()):
            stats = ("-" if not group_stats["episodes"] else
                     f"return {group_stats['mean_return']:7.3f}  success {group_stats['success_rate']:.2f}  "
                     f"steps {group_stats['mean_steps']:6.1f}")
            envs = f", {group_stats['num_envs']} envs" if group_stats["num_envs"] > 1 else ""
            print(f"  {group:{width}s}  {group_stats['episodes']:6d}  {stats}  "
                  f"({group_stats['incomplete']} incomplete{envs})")
        total = sum(e["episodes"] for e in groups.values())
        if len(groups) > 1 and total:
            ret = sum(e["mean_return"] * e["episodes"] for e in groups.values() if e["episodes"]) / total
            succ = sum(e["success_rate"] * e["episodes"] for e in groups.values() if e["episodes"]) / total
            print(f"  {'all':{width}s}  {total:6d}  return {ret:7.3f}  success {succ:.2f}")
    return 0
