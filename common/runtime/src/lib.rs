//! surfstream-runtime: how a graph runs: the node contract ([`node`]), graph files
//! ([`graph`]), the iceoryx2 transport ([`ipc`]), the in-process transport ([`inproc`]), the
//! process shell every node binary uses ([`shell`]), latency statistics ([`latency`]), the
//! memory plan and the allocator under a memory budget ([`memory`]), liveness: heartbeats, the
//! stall watch, the launcher check ([`watchdog`]), per-user launch slots ([`slots`]), the stop
//! signals of every verb ([`stop`]) and standard streams that cannot be written ([`stdio`]).
//!
//! Not for: what a node computes (the node crates, which know nothing of the transport), file
//! formats (surfstream-io), or the CLI and the end of a run: starting and supervising
//! processes, run.json, Table 6 and the report are the launcher's (`launch/`;
//! docs/architecture.md §3, §4).

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
