//! surfstream-runtime: how a graph runs: the node contract ([`node`]), graph files
//! ([`graph`]), the iceoryx2 transport ([`ipc`]), the in-process transport ([`inproc`]), the
//! process shell every node binary uses ([`shell`]), latency statistics ([`latency`]), the allocator under a memory budget ([`memory`]) and
//! liveness: heartbeats, the stall watch, the launcher check ([`watchdog`]), per-user launch
//! slots ([`slots`]) and the stop signals of every verb ([`stop`]).

pub mod graph;
pub mod inproc;
pub mod ipc;
pub mod latency;
pub mod memory;
pub mod node;
pub mod shell;
pub mod slots;
pub mod stdio;
pub mod stop;
pub mod watchdog;
