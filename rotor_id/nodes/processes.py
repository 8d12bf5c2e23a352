"""
Start the installed nodes as separate processes on an isolated DDS domain, and stop them cleanly.

What ``rotor-id demo`` and the multi-process tests share (they run where only the rclpy wheels
are installed, without launch/launch_ros): the executables are found like ``ros2 run`` finds
them (ament index prefix + lib/rotor_id/<name>), every child leads its own process group (so a
terminal's Ctrl-C reaches the caller, which stops the children in order: the recorder last,
after every publisher has had its messages acknowledged, so the bag holds everything and is
finalised) and the same ROS_DOMAIN_ID with ROS_AUTOMATIC_DISCOVERY_RANGE=LOCALHOST.
"""

import os
from pathlib import Path
import signal
import subprocess
import time

#: The five nodes, in the order they are started (the plant last: it waits for subscribers).
NODES = ('identifier', 'state_estimator', 'recorder', 'stirring_input', 'rotor_plant')


def executable(name, package='rotor_id'):
    """Path of an installed executable, found like ``ros2 run`` (FileNotFoundError if absent)."""
    try:
        from ament_index_python.packages import get_package_prefix
        prefix = Path(get_package_prefix(package))
    except (ImportError, LookupError, ValueError) as exc:
        raise FileNotFoundError(f'package {package} is not in the ament index ({exc}); build '
                                'the workspace (make build) and run through ./rotor-id') from None
    path = prefix / 'lib' / package / name
    if not os.access(path, os.X_OK):
        raise FileNotFoundError(f'no executable {path}: rebuild the workspace (make build)')
    return path


#: Fast DDS participant profile for the processes we start: announce every 200 ms for the
#: first 4 s and every 1 s after (defaults: 5 quick announcements, then every 3 s). Five
#: nodes and a watcher start together on a loaded machine; when the quick announcements
#: cross a participant that is not up yet, the defaults leave it undiscovered for 3 s,
#: longer than the demo's whole run (the demo then showed no stirring phases). And a
#: shared-memory port of 16384 messages in an 8 MiB segment (defaults: 512 in 512 KiB): the
#: default port holds 0.17 s of three 1 kHz sensor topics, and on a loaded machine a reader
#: not scheduled for longer lost the samples beyond it (windows INCOMPLETE in CI).
QUICK_DISCOVERY_XML = """<?xml version="1.0" encoding="UTF-8" ?>
<profiles xmlns="http://www.eprosima.com/XMLSchemas/fastRTPS_Profiles">
  <transport_descriptors>
    <transport_descriptor>
      <transport_id>rotor_id_shm</transport_id>
      <type>SHM</type>
      <segment_size>8388608</segment_size>
      <port_queue_capacity>16384</port_queue_capacity>
    </transport_descriptor>
    <transport_descriptor>
      <transport_id>rotor_id_udp</transport_id>
      <type>UDPv4</type>
    </transport_descriptor>
  </transport_descriptors>
  <participant profile_name="rotor_id_quick_discovery" is_default_profile="true">
    <rtps>
      <userTransports>
        <transport_id>rotor_id_shm</transport_id>
        <transport_id>rotor_id_udp</transport_id>
      </userTransports>
      <useBuiltinTransports>false</useBuiltinTransports>
      <builtin>
        <discovery_config>
          <initialAnnouncements>
            <count>20</count>
            <period><nanosec>200000000</nanosec></period>
          </initialAnnouncements>
          <leaseAnnouncement><sec>1</sec></leaseAnnouncement>
          <leaseDuration><sec>10</sec></leaseDuration>
        </discovery_config>
      </builtin>
    </rtps>
  </participant>
</profiles>
"""
#: Seconds a node that did not stop in time gets to write its threads' stacks before SIGKILL.
STACK_DUMP_WAIT_S = 2.0
_PROFILE_VARS = ('FASTRTPS_DEFAULT_PROFILES_FILE', 'FASTDDS_DEFAULT_PROFILES_FILE')


def isolated_env(domain_id, log_dir, base=None):
    """
    Environment for ROS children: own domain, loopback discovery, logs in ``log_dir``.

    With Fast DDS (the Jazzy default) and no profile of the user's, the children also get
    :data:`QUICK_DISCOVERY_XML` (written to ``log_dir``).
    """
    env = dict(os.environ if base is None else base)
    env['ROS_DOMAIN_ID'] = str(int(domain_id))
    env['ROS_AUTOMATIC_DISCOVERY_RANGE'] = 'LOCALHOST'
    env['ROS_LOG_DIR'] = str(log_dir)
    env['PYTHONUNBUFFERED'] = '1'
    fastdds = env.get('RMW_IMPLEMENTATION', 'rmw_fastrtps_cpp').startswith('rmw_fastrtps')
    if fastdds and not any(env.get(v) for v in _PROFILE_VARS):
        profile = Path(log_dir) / 'fastdds_quick_discovery.xml'
        profile.parent.mkdir(parents=True, exist_ok=True)
        profile.write_text(QUICK_DISCOVERY_XML)
        env['FASTRTPS_DEFAULT_PROFILES_FILE'] = str(profile)
    return env


def ros_argument(value):
    """Format a parameter value for ``-p name:=value`` (YAML: lists, floats, booleans)."""
    if isinstance(value, bool):
        return 'true' if value else 'false'
    if isinstance(value, (list, tuple)):
        return '[' + ', '.join(ros_argument(v) for v in value) + ']'
    if isinstance(value, float):
        return repr(value)
    return str(value)


def _tree_cpu_s(pid):
    """User + system CPU s of a process and its live descendants (nan without /proc)."""
    tick = os.sysconf('SC_CLK_TCK')
    total, todo, root = 0.0, [pid], pid
    while todo:
        pid = todo.pop()
        try:
            # the fields after the command name (which may hold spaces): utime, stime 14, 15
            fields = Path(f'/proc/{pid}/stat').read_text().rsplit(')', 1)[1].split()
            total += (int(fields[11]) + int(fields[12])) / tick
            for task in Path(f'/proc/{pid}/task').iterdir():
                todo += [int(c) for c in (task / 'children').read_text().split()]
        except (OSError, ValueError, IndexError):
            if pid == root:             # a descendant that just exited is no error
                return float('nan')
    return total


#: How long a stopped node may take to exit before it is killed: its own clean-up is bounded
#: by about 13 s (common.ACK_WAIT_S for a lagging reader, the tick thread, the executor), and
#: a loaded machine (the test suite on two cores) stretches every step of it.
STOP_TIMEOUT_S = 30.0


class NodeProcesses:
    """The node processes of one run; a context manager that never leaves one running."""

    def __init__(self, env, log_dir, prefix=()):
        self.env = env
        self.log_dir = Path(log_dir)
        self.log_dir.mkdir(parents=True, exist_ok=True)
        self.prefix = list(prefix)
        self.procs = {}
        self.logs = {}
        self.stop_s = {}        # seconds from the stop signal to the exit, per process
        self._signalled = {}

    def start(self, name, params_file=None, params=None, node=None, namespace=None,
              ros_args=(), cwd=None):
        """
        Start executable ``node`` (default ``name``) with a parameter file and ``-p`` overrides.

        ``namespace`` (e.g. '/rig2') is given as ``-r __ns:=``: with the rig's relative topic
        names it moves the whole rig. ``ros_args`` are appended as given (a command line's
        ``--ros-args`` part); ``cwd`` is the working directory (relative paths in parameters).
        """
        cmd = self.prefix + [str(executable(node or name)), '--ros-args']
        if namespace:
            cmd += ['-r', f'__ns:={namespace}']
        if params_file:
            cmd += ['--params-file', str(params_file)]
        for key, value in (params or {}).items():
            cmd += ['-p', f'{key}:={ros_argument(value)}']
        cmd += list(ros_args)
        log = open(self.log_dir / f'{name}.log', 'w')
        self.logs[name] = log
        self.procs[name] = subprocess.Popen(cmd, env=self.env, stdout=log, cwd=cwd,
                                            stderr=subprocess.STDOUT, start_new_session=True)
        return self.procs[name]

    def log(self, name):
        """Text of a process's output so far."""
        if not self.logs[name].closed:
            self.logs[name].flush()
        return (self.log_dir / f'{name}.log').read_text(errors='replace')

    def cpu_s(self):
        """
        CPU seconds used so far by each running process and its descendants (Linux /proc).

        Read before stopping: a process's CPU is gone with it. ``nan`` where /proc cannot say.
        """
        return {name: _tree_cpu_s(proc.pid) for name, proc in self.procs.items()
                if proc.poll() is None}

    def dead(self):
        """Names of processes that exited, with their return codes."""
        return {n: p.returncode for n, p in self.procs.items() if p.poll() is not None}

    def stop(self, name, sig=signal.SIGINT, timeout=STOP_TIMEOUT_S):
        """
        Signal one process and wait for it (SIGKILL after ``timeout``); return its code.

        ``sig`` None: only wait (it was signalled already).
        """
        proc = self.procs[name]
        if proc.poll() is None:
            if sig is not None:
                self._signalled[name] = time.monotonic()
                proc.send_signal(sig)
            try:
                proc.wait(timeout)
            except subprocess.TimeoutExpired:
                # where it hangs, into its log (rotor_id.nodes.common.spin_node), then kill
                proc.send_signal(signal.SIGUSR1)
                try:
                    proc.wait(STACK_DUMP_WAIT_S)
                except subprocess.TimeoutExpired:
                    pass
                proc.kill()
                proc.wait()
            self.stop_s[name] = time.monotonic() - self._signalled.get(name, time.monotonic())
        return proc.returncode

    def stop_all(self, last=('recorder',), timeout=STOP_TIMEOUT_S):
        """
        Stop every process but ``last`` together, then ``last`` in order; return exit codes.

        The publishers go first: each waits until reliable readers (the recorder) acknowledged
        what it sent, so the recorder, stopped last, finds its topics quiet and drains quickly.
        """
        codes = {}
        rest = [n for n in self.procs if n not in last]
        for name in rest:
            if self.procs[name].poll() is None:
                self._signalled[name] = time.monotonic()
                self.procs[name].send_signal(signal.SIGINT)
        deadline = time.monotonic() + timeout
        for name in rest:
            codes[name] = self.stop(name, None, timeout=max(0.1, deadline - time.monotonic()))
        for name in last:
            if name in self.procs:
                codes[name] = self.stop(name, timeout=timeout)
        for log in self.logs.values():
            log.close()
        return codes

    def exit_summary(self, tail=15):
        """Each process's exit code and seconds from its stop signal; the log tail of failures."""
        lines = []
        for name, proc in self.procs.items():
            code = proc.poll()
            took = self.stop_s.get(name)
            lines.append(f'{name}: exit {code}' + (f' {took:.1f} s after the stop signal'
                                                   if took is not None else ''))
            if code != 0:
                lines += ['    ' + line for line in self.log(name).splitlines()[-tail:]]
        return '\n'.join(lines)

    def __enter__(self):
        """Return self."""
        return self

    def __exit__(self, *exc):
        """Stop whatever still runs."""
        if any(p.poll() is None for p in self.procs.values()):
            self.stop_all()
        return False
