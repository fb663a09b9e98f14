//! `planet-bench`: benchmarks of the planet system.
//!
//! - `flight`: fly a trajectory with a headless streaming client against an
//!   in-process server behind a simulated link, per link: CSV, PNG plots and
//!   a summary table (error against run time and bytes).
//! - `resident`: CPU time of the client's per-frame selection and scheduling
//!   with at least 10 000 resident blocks (synthetic tree, no network).
//! - `server`: QUIC request throughput and latency against nginx (HTTPS
//!   byte ranges) on the same file and request list.
//! - `load`: 1000 lightweight streaming clients against one server.
//! - `hostile`: hostile clients of each kind (zero window, half-open, bad
//!   token) against one server while a good client streams.
//! - `soak`: hours of steady streaming with connection churn; the server's
//!   memory and descriptors must stay flat, with no error.

// libc calls for /proc accounting and thread CPU time; h2 removes these
// (rustix), and with them this opt-out of the workspace `unsafe_code = "deny"`.
#![allow(unsafe_code)]

mod children;
mod flight;
mod hostile;
mod load;
mod plot;
mod resident;
mod server;
mod soak;

use anyhow::Result;
use clap::{Parser, Subcommand};

/// mimalloc, like `planet-server` and `planet-view`: the client side of the
/// benchmarks (quinn, hyper, the decoder) is allocation-heavy, and the
/// figures should be those of the shipped binaries.
#[global_allocator]
static GLOBAL: mimalloc::MiMalloc = mimalloc::MiMalloc;

#[derive(Parser)]
#[command(
    name = "planet-bench",
    about = "Benchmarks of the planet streaming system"
)]
struct Cli {
    #[command(subcommand)]
    command: Command,
}

#[derive(Subcommand)]
enum Command {
    /// Fly a trajectory over real QUIC through simulated links.
    Flight(flight::FlightArgs),
    /// Selection + scheduling CPU per frame with ≥ 10 000 resident blocks.
    Resident(resident::ResidentArgs),
    /// QUIC request throughput and latency of planet-server, against nginx
    /// serving the same file over HTTPS byte ranges (--nginx).
    Server(server::ServerArgs),
    /// Many lightweight streaming clients against one server: load held,
    /// latency, errors, server CPU and memory per connection.
    Load(load::LoadArgs),
    /// Hostile clients (zero window, half-open, bad token) against one
    /// server while a good client streams: its throughput and connect time,
    /// the server's memory per hostile connection.
    Hostile(hostile::HostileArgs),
    /// Hours of steady streaming with connection churn: the server's memory
    /// and descriptors must stay flat, with no error.
    Soak(soak::SoakArgs),
}

fn main() -> Result<()> {
    planet_core::pages::no_transparent_huge_pages();
    planet_core::pipe::exit_quietly_on_broken_pipe();
    children::stop_with_signals();
    let cli = Cli::parse();
    match cli.command {
        Command::Flight(a) => flight::run(a),
        Command::Resident(a) => resident::run(a),
        Command::Server(a) => server::run(a),
        Command::Load(a) => load::run(a),
        Command::Hostile(a) => hostile::run(a),
        Command::Soak(a) => soak::run(a),
    }
}

/// CPU time consumed by the calling thread.
pub fn thread_cpu() -> std::time::Duration {
    cpu_time::ThreadTime::now().as_duration()
}
