//! The only code in sdsem that opens a port to the stage controller: a serial
//! device (or a pseudo-terminal, which opens the same way) or a TCP connection.

use std::io;
use std::path::PathBuf;
use std::pin::Pin;
use std::task::{Context, Poll};
use std::time::Duration;

use tokio::io::{AsyncRead, AsyncWrite, ReadBuf};
use tokio::net::TcpStream;
use tokio_serial::{SerialPortBuilderExt, SerialStream};
use tracing::{debug, info};

use super::error::StageError;

/// Where the controller is, parsed from the configuration's `stage.endpoint`.
#[derive(Clone, Debug, PartialEq, Eq)]
pub enum Endpoint {
    /// `tcp://HOST:PORT`.
    Tcp(String),
    /// A serial device or pty path: `/dev/ttyUSB0`, or `serial:///dev/ttyUSB0`.
    Serial(PathBuf),
}

impl Endpoint {
    /// Parses an endpoint string.
    pub fn parse(endpoint: &str) -> Result<Self, StageError> {
        let bad = |reason: &str| StageError::Config {
            field: "stage.endpoint",
            reason: format!("{endpoint:?}: {reason}"),
        };
        if let Some(addr) = endpoint.strip_prefix("tcp://") {
            let port_ok = addr
                .rsplit_once(':')
                .is_some_and(|(host, port)| !host.is_empty() && port.parse::<u16>().is_ok());
            return if port_ok {
                Ok(Self::Tcp(addr.to_owned()))
            } else {
                Err(bad("write tcp://HOST:PORT, e.g. tcp://127.0.0.1:40123"))
            };
        }
        let path = endpoint.strip_prefix("serial://").unwrap_or(endpoint);
        if path.starts_with('/') {
            Ok(Self::Serial(PathBuf::from(path)))
        } else {
            Err(bad(
                "write a serial device path (/dev/ttyUSB0, /dev/serial/by-id/…) or tcp://HOST:PORT",
            ))
        }
    }
}

/// An open link to the controller: a byte stream the driver reads and writes.
#[derive(Debug)]
pub enum StageLink {
    /// A TCP connection.
    Tcp(TcpStream),
    /// A serial port or pseudo-terminal.
    Serial(SerialLink),
}

/// A serial port opened exclusively (one owner per resource); the exclusive flag
/// is cleared on drop so that the next session can open the port even when
/// another process keeps it open (a simulator holding its pty, DESIGN §8).
#[derive(Debug)]
pub struct SerialLink(SerialStream);

impl Drop for SerialLink {
    fn drop(&mut self) {
        if let Err(e) = self.0.set_exclusive(false) {
            debug!(error = %e, "could not clear the serial port's exclusive flag");
        }
    }
}

/// Opens the stage link described by `endpoint`; a serial line at `baud`
/// ([`super::StageConfig::effective_baud`]), which it needs.
pub async fn open(
    endpoint: &str,
    baud: Option<u32>,
    connect_timeout: Duration,
) -> Result<StageLink, StageError> {
    match Endpoint::parse(endpoint)? {
        Endpoint::Tcp(addr) => {
            let connected = tokio::time::timeout(connect_timeout, TcpStream::connect(&addr)).await;
            let stream = match connected {
                Ok(Ok(s)) => s,
                Ok(Err(e)) => return Err(tcp_error(endpoint, &e)),
                Err(_) => {
                    return Err(StageError::Open {
                        endpoint: endpoint.to_owned(),
                        cause: format!("no connection within {connect_timeout:?}"),
                        remedy: "check the host address and that the network reaches it".into(),
                    });
                }
            };
            // One small command at a time: do not let Nagle hold it back.
            stream
                .set_nodelay(true)
                .map_err(|e| tcp_error(endpoint, &e))?;
            info!(endpoint, "stage link open (TCP)");
            Ok(StageLink::Tcp(stream))
        }
        Endpoint::Serial(path) => {
            let baud = baud.ok_or_else(|| StageError::Config {
                field: "stage.baud",
                reason: format!(
                    "{endpoint} is a serial line, and stage.protocol has no usual serial rate: \
                     set stage.baud"
                ),
            })?;
            // On a pseudo-terminal the baud rate does nothing (DESIGN §8); harmless.
            // 8N1 without flow control: PI controllers and RemCon32 alike [SF, ML].
            let port = tokio_serial::new(path.to_string_lossy(), baud)
                .data_bits(tokio_serial::DataBits::Eight)
                .parity(tokio_serial::Parity::None)
                .stop_bits(tokio_serial::StopBits::One)
                .flow_control(tokio_serial::FlowControl::None)
                .timeout(connect_timeout)
                .open_native_async()
                .map_err(|e| serial_error(endpoint, &e))?;
            info!(endpoint, baud, "stage link open (serial)");
            Ok(StageLink::Serial(SerialLink(port)))
        }
    }
}

fn tcp_error(endpoint: &str, e: &io::Error) -> StageError {
    let remedy = match e.kind() {
        io::ErrorKind::ConnectionRefused => {
            "nothing listens there: is the simulator running (sdsem-sim prints `stage tcp://…`), \
             or the controller's TCP interface enabled, and is the port right?"
        }
        io::ErrorKind::TimedOut
        | io::ErrorKind::HostUnreachable
        | io::ErrorKind::NetworkUnreachable => {
            "check the host address and that the network reaches it"
        }
        _ => "check stage.endpoint",
    };
    StageError::Open {
        endpoint: endpoint.to_owned(),
        cause: e.to_string(),
        remedy: remedy.into(),
    }
}

fn serial_error(endpoint: &str, e: &tokio_serial::Error) -> StageError {
    use tokio_serial::ErrorKind;
    let remedy = match e.kind() {
        ErrorKind::Io(io::ErrorKind::NotFound) => {
            "no such device: is the controller plugged in and powered? `ls /dev/serial/by-id/` \
             lists the serial adapters; with the simulator, use the path it printed"
        }
        ErrorKind::Io(io::ErrorKind::PermissionDenied) => {
            "permission denied: is the user in group dialout? (`sudo usermod -aG dialout $USER`, \
             then log in again; the service needs SupplementaryGroups=dialout)"
        }
        ErrorKind::NoDevice => {
            "the port is busy: another program holds it (PIMikroMove, a terminal program, another \
             sdsem): close it"
        }
        _ => "check stage.endpoint and stage.baud",
    };
    StageError::Open {
        endpoint: endpoint.to_owned(),
        cause: e.to_string(),
        remedy: remedy.into(),
    }
}

impl AsyncRead for StageLink {
    fn poll_read(
        self: Pin<&mut Self>,
        cx: &mut Context<'_>,
        buf: &mut ReadBuf<'_>,
    ) -> Poll<io::Result<()>> {
        match self.get_mut() {
            Self::Tcp(s) => Pin::new(s).poll_read(cx, buf),
            Self::Serial(s) => Pin::new(&mut s.0).poll_read(cx, buf),
        }
    }
}

impl AsyncWrite for StageLink {
    fn poll_write(
        self: Pin<&mut Self>,
        cx: &mut Context<'_>,
        buf: &[u8],
    ) -> Poll<io::Result<usize>> {
        match self.get_mut() {
            Self::Tcp(s) => Pin::new(s).poll_write(cx, buf),
            Self::Serial(s) => Pin::new(&mut s.0).poll_write(cx, buf),
        }
    }

    fn poll_flush(self: Pin<&mut Self>, cx: &mut Context<'_>) -> Poll<io::Result<()>> {
        match self.get_mut() {
            Self::Tcp(s) => Pin::new(s).poll_flush(cx),
            Self::Serial(s) => Pin::new(&mut s.0).poll_flush(cx),
        }
    }

    fn poll_shutdown(self: Pin<&mut Self>, cx: &mut Context<'_>) -> Poll<io::Result<()>> {
        match self.get_mut() {
            Self::Tcp(s) => Pin::new(s).poll_shutdown(cx),
            Self::Serial(s) => Pin::new(&mut s.0).poll_shutdown(cx),
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn parses_endpoints() {
        assert_eq!(
            Endpoint::parse("tcp://127.0.0.1:4000").unwrap(),
            Endpoint::Tcp("127.0.0.1:4000".into())
        );
        assert_eq!(
            Endpoint::parse("tcp://stage.lab:50000").unwrap(),
            Endpoint::Tcp("stage.lab:50000".into())
        );
        assert_eq!(
            Endpoint::parse("/dev/ttyUSB0").unwrap(),
            Endpoint::Serial("/dev/ttyUSB0".into())
        );
        assert_eq!(
            Endpoint::parse("serial:///dev/pts/3").unwrap(),
            Endpoint::Serial("/dev/pts/3".into())
        );
        for bad in [
            "",
            "ttyUSB0",
            "tcp://127.0.0.1",
            "tcp://:80",
            "udp://x:1",
            "tcp://h:99999",
        ] {
            let e = Endpoint::parse(bad).unwrap_err().to_string();
            assert!(e.contains("stage.endpoint"), "{bad}: {e}");
        }
    }

    #[tokio::test]
    async fn missing_device_names_the_device_and_the_remedy() {
        let e = open(
            "/dev/does-not-exist-sdsem",
            Some(115_200),
            Duration::from_secs(1),
        )
        .await
        .unwrap_err()
        .to_string();
        assert!(e.contains("/dev/does-not-exist-sdsem"), "{e}");
        assert!(e.contains("plugged in"), "{e}");
        // A protocol without a serial line and no stage.baud: said before opening anything.
        let e = open("/dev/does-not-exist-sdsem", None, Duration::from_secs(1))
            .await
            .unwrap_err()
            .to_string();
        assert!(e.contains("set stage.baud"), "{e}");
    }

    #[tokio::test]
    async fn refused_tcp_connection_suggests_starting_the_simulator() {
        // Bind then drop a listener: its port is very likely closed now.
        let port = std::net::TcpListener::bind("127.0.0.1:0")
            .unwrap()
            .local_addr()
            .unwrap()
            .port();
        let endpoint = format!("tcp://127.0.0.1:{port}");
        let e = open(&endpoint, Some(115_200), Duration::from_secs(1))
            .await
            .unwrap_err()
            .to_string();
        assert!(e.contains(&endpoint), "{e}");
        assert!(e.contains("simulator"), "{e}");
    }

    #[tokio::test]
    async fn opens_a_pseudo_terminal_like_a_serial_port_twice_in_a_row() {
        use tokio::io::{AsyncReadExt, AsyncWriteExt};
        // The simulator's side of a pty: master plus a slave it keeps open.
        let (mut master, _slave) = serialport::TTYPort::pair().unwrap();
        let path = serialport::SerialPort::name(&_slave).unwrap();
        for _ in 0..2 {
            let mut link = open(&path, Some(115_200), Duration::from_secs(1))
                .await
                .unwrap();
            link.write_all(b"ERR?\n").await.unwrap();
            let mut got = [0u8; 5];
            std::io::Read::read_exact(&mut master, &mut got).unwrap();
            assert_eq!(&got, b"ERR?\n");
            std::io::Write::write_all(&mut master, b"0\n").unwrap();
            let mut reply = [0u8; 2];
            link.read_exact(&mut reply).await.unwrap();
            assert_eq!(&reply, b"0\n");
        }
    }
}
