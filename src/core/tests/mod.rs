//! Virtual-time tests of the channel core: rule by rule against the seeds, then properties over
//! random input sequences.

mod autotune;
mod bank;
mod failsafe;
mod harness;
mod heater;
mod mpc;
mod props;
mod rules;
mod timebase;
mod vendor;
