//! The node tells systemd when it is up (`READY=1`) and when it stops (`STOPPING=1`), over the
//! socket named by `NOTIFY_SOCKET`, as systemd does for a `Type=notify` unit; here the test
//! plays systemd with its own datagram socket.

use crate::ros_harness::*;
use nix::sys::signal::Signal;
use std::os::unix::net::UnixDatagram;
use std::time::Duration;

fn recv(sock: &UnixDatagram) -> Option<String> {
    let mut buf = [0u8; 256];
    let n = sock.recv(&mut buf).ok()?;
    Some(String::from_utf8_lossy(&buf[..n]).into_owned())
}

#[test]
fn ready_once_running_and_stopping_on_sigterm() {
    let dir = std::env::temp_dir().join(format!("pwm_notify_{}", std::process::id()));
    std::fs::create_dir_all(&dir).unwrap();
    let path = dir.join("notify.sock");
    let sock = UnixDatagram::bind(&path).unwrap();
    sock.set_read_timeout(Some(Duration::from_secs(30)))
        .unwrap();

    let node = NodeProc::start_with(&[], &[("NOTIFY_SOCKET", path.to_str().unwrap())]);
    let ready = recv(&sock);
    assert_eq!(ready.as_deref(), Some("READY=1\n"), "{}", node.log());
    // Sent after the start-up line that says the node runs (read by another thread, so it
    // may need a moment to show up here).
    assert!(node.wait_log("running:", LONG), "{}", node.log());

    let (status, log) = node.stop_with(Signal::SIGTERM);
    assert_eq!(status.code(), Some(0), "{log}");
    assert_eq!(recv(&sock).as_deref(), Some("STOPPING=1\n"), "{log}");
    std::fs::remove_dir_all(&dir).unwrap();
}
