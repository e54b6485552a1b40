//! Transports from one URL, as MAVProxy and the mavlink crate write them.
//!
//! | URL | what |
//! |---|---|
//! | `serial:/dev/ttyUSB0:57600` | a serial device (3DR/SiK radio, USB) at a baud rate |
//! | `udpin:0.0.0.0:14550` | listen for UDP (where PX4 SITL sends to a GCS); replies go to the last sender |
//! | `udpout:HOST:PORT` | send UDP to a fixed peer, receive its answers |
//! | `tcpout:HOST:PORT` | TCP client (ArduPilot SITL's `tcp:5760`) |
//! | `tcpin:ADDR:PORT` | TCP server: the vehicle link takes the first client; a forward endpoint ([`super::router`]) serves every client |
//!
//! The connection is the mavlink crate's async one, set to receive MAVLink 1
//! and 2 frames alike and, with a key, to sign what it sends and check
//! what it receives.
//!
//! A `udpin:` socket is bound once ([`bind_udp_in`], or handed in already
//! bound) and kept for the link's life: each (re)connection parses
//! datagrams from a duplicate of it (the mavlink crate's
//! `UdpConfig::from_socket`), so `udpin:127.0.0.1:0` keeps the port the
//! kernel chose and the caller can read it (`LinkHandle::bound_addr`).

use std::fmt;
use std::io;
use std::net::UdpSocket;
use std::str::FromStr;

use mavlink::dialects::common::MavMessage;
use mavlink::{
    AsyncConnectable, AsyncConnection, AsyncMavConnection, ConnectionAddress, MavlinkVersion,
    SerialConfig, SigningConfig, TcpConfig, TcpMode, UdpConfig, UdpMode,
};
use serde::{Deserialize, Serialize};

use super::error::LinkError;

/// The async connection the link actor owns.
pub type Connection = AsyncConnection<MavMessage>;

/// A parsed link URL.
#[derive(Debug, Clone, PartialEq, Eq)]
pub enum LinkUrl {
    /// `serial:PATH:BAUD`
    Serial {
        /// Device path.
        path: String,
        /// Baud rate.
        baud: u32,
    },
    /// `udpin:ADDR:PORT`
    UdpIn {
        /// Local address to bind.
        addr: String,
    },
    /// `udpout:HOST:PORT`
    UdpOut {
        /// Peer address.
        addr: String,
    },
    /// `tcpout:HOST:PORT`
    TcpOut {
        /// Peer address.
        addr: String,
    },
    /// `tcpin:ADDR:PORT`
    TcpIn {
        /// Local address to listen on.
        addr: String,
    },
}

fn bad(url: &str, reason: &str) -> LinkError {
    LinkError::BadUrl {
        url: url.to_string(),
        reason: reason.to_string(),
    }
}

fn host_port(url: &str, rest: &str) -> Result<String, LinkError> {
    let (host, port) = rest
        .rsplit_once(':')
        .ok_or_else(|| bad(url, "expected HOST:PORT"))?;
    if host.is_empty() {
        return Err(bad(url, "empty host"));
    }
    port.parse::<u16>()
        .map_err(|_| bad(url, "port is not a number in 0..=65535"))?;
    Ok(rest.to_string())
}

impl FromStr for LinkUrl {
    type Err = LinkError;

    fn from_str(url: &str) -> Result<Self, LinkError> {
        let (scheme, rest) = url
            .split_once(':')
            .ok_or_else(|| bad(url, "expected SCHEME:..."))?;
        match scheme {
            "serial" => {
                let (path, baud) = rest
                    .rsplit_once(':')
                    .ok_or_else(|| bad(url, "expected serial:PATH:BAUD"))?;
                if path.is_empty() {
                    return Err(bad(url, "empty device path"));
                }
                let baud = baud
                    .parse::<u32>()
                    .ok()
                    .filter(|b| *b > 0)
                    .ok_or_else(|| bad(url, "baud rate is not a positive number"))?;
                Ok(Self::Serial {
                    path: path.to_string(),
                    baud,
                })
            }
            "udpin" => Ok(Self::UdpIn {
                addr: host_port(url, rest)?,
            }),
            "udpout" => Ok(Self::UdpOut {
                addr: host_port(url, rest)?,
            }),
            "tcpout" => Ok(Self::TcpOut {
                addr: host_port(url, rest)?,
            }),
            "tcpin" => Ok(Self::TcpIn {
                addr: host_port(url, rest)?,
            }),
            _ => Err(bad(
                url,
                "scheme must be serial, udpin, udpout, tcpout or tcpin",
            )),
        }
    }
}

impl fmt::Display for LinkUrl {
    fn fmt(&self, f: &mut fmt::Formatter<'_>) -> fmt::Result {
        match self {
            Self::Serial { path, baud } => write!(f, "serial:{path}:{baud}"),
            Self::UdpIn { addr } => write!(f, "udpin:{addr}"),
            Self::UdpOut { addr } => write!(f, "udpout:{addr}"),
            Self::TcpOut { addr } => write!(f, "tcpout:{addr}"),
            Self::TcpIn { addr } => write!(f, "tcpin:{addr}"),
        }
    }
}

/// MAVLink 2 signing: the shared secret and this link's id.
#[derive(Debug, Clone, PartialEq, Eq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct Signing {
    /// The 32-byte secret key as 64 hex digits.
    pub key_hex: String,
    /// The link id written into our signatures.
    #[serde(default)]
    pub link_id: u8,
    /// Accept unsigned (and MAVLink 1) frames from the vehicle.
    #[serde(default)]
    pub allow_unsigned: bool,
}

impl Signing {
    /// Decodes the key.
    pub fn key(&self) -> Result<[u8; 32], LinkError> {
        let hex = self.key_hex.trim();
        if hex.len() != 64 {
            return Err(LinkError::BadSigningKey {
                reason: format!("expected 64 hex digits, got {}", hex.len()),
            });
        }
        let mut key = [0u8; 32];
        for (i, byte) in key.iter_mut().enumerate() {
            let pair = hex
                .get(2 * i..2 * i + 2)
                .ok_or_else(|| LinkError::BadSigningKey {
                    reason: "not ASCII hex".into(),
                })?;
            *byte = u8::from_str_radix(pair, 16).map_err(|_| LinkError::BadSigningKey {
                reason: format!("`{pair}` is not a hex byte"),
            })?;
        }
        Ok(key)
    }

    fn config(&self) -> Result<SigningConfig, LinkError> {
        Ok(SigningConfig::new(
            self.key()?,
            self.link_id,
            true,
            self.allow_unsigned,
        ))
    }
}

/// Binds the socket of a `udpin:` URL (port 0: one the kernel picks; read
/// it with `local_addr`). None for the other schemes, which open on
/// connecting.
pub async fn bind_udp_in(url: &LinkUrl) -> io::Result<Option<UdpSocket>> {
    match url {
        LinkUrl::UdpIn { addr } => {
            let socket = tokio::net::UdpSocket::bind(addr.as_str()).await?;
            Ok(Some(socket.into_std()?))
        }
        _ => Ok(None),
    }
}

/// Opens the transport and sets it up: receive MAVLink 1 and 2, send
/// `version`, sign with `signing`. A `udpin:` URL reads and writes through
/// `udp_in` (bound by [`bind_udp_in`] or by the caller; the socket stays
/// the caller's, the connection uses a duplicate) and fails without it.
pub async fn connect(
    url: &LinkUrl,
    udp_in: Option<&UdpSocket>,
    version: MavlinkVersion,
    signing: Option<&Signing>,
) -> io::Result<Connection> {
    let address = match url {
        LinkUrl::Serial { path, baud } => {
            ConnectionAddress::Serial(SerialConfig::new(path.clone(), *baud))
        }
        LinkUrl::UdpIn { addr } => {
            let socket = udp_in.ok_or_else(|| {
                io::Error::new(
                    io::ErrorKind::NotConnected,
                    format!("udpin:{addr}: the socket is not bound"),
                )
            })?;
            ConnectionAddress::Udp(UdpConfig::from_socket(socket.try_clone()?, UdpMode::Udpin)?)
        }
        LinkUrl::UdpOut { addr } => {
            ConnectionAddress::Udp(UdpConfig::new(addr.clone(), UdpMode::Udpout))
        }
        LinkUrl::TcpOut { addr } => {
            ConnectionAddress::Tcp(TcpConfig::new(addr.clone(), TcpMode::TcpOut))
        }
        LinkUrl::TcpIn { addr } => {
            ConnectionAddress::Tcp(TcpConfig::new(addr.clone(), TcpMode::TcpIn))
        }
    };
    let signing = match signing {
        Some(s) => Some(
            s.config()
                .map_err(|e| io::Error::new(io::ErrorKind::InvalidInput, e.to_string()))?,
        ),
        None => None,
    };
    let mut conn: Connection = address.connect_async::<MavMessage>().await?;
    conn.set_protocol_version(version);
    conn.set_allow_recv_any_version(true);
    conn.setup_signing(signing);
    Ok(conn)
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn parses_the_four_schemes() {
        assert_eq!(
            "serial:/dev/ttyUSB0:57600".parse::<LinkUrl>().ok(),
            Some(LinkUrl::Serial {
                path: "/dev/ttyUSB0".into(),
                baud: 57600
            })
        );
        assert_eq!(
            "udpin:0.0.0.0:14550".parse::<LinkUrl>().ok(),
            Some(LinkUrl::UdpIn {
                addr: "0.0.0.0:14550".into()
            })
        );
        assert_eq!(
            "udpout:127.0.0.1:14540".parse::<LinkUrl>().ok(),
            Some(LinkUrl::UdpOut {
                addr: "127.0.0.1:14540".into()
            })
        );
        assert_eq!(
            "tcpout:localhost:5760".parse::<LinkUrl>().ok(),
            Some(LinkUrl::TcpOut {
                addr: "localhost:5760".into()
            })
        );
        for s in [
            "serial:/dev/ttyUSB0:57600",
            "udpin:0.0.0.0:14550",
            "tcpout:localhost:5760",
            "tcpin:0.0.0.0:5760",
        ] {
            assert_eq!(
                s.parse::<LinkUrl>().map(|u| u.to_string()).ok().as_deref(),
                Some(s)
            );
        }
    }

    #[test]
    fn refuses_bad_urls() {
        for s in [
            "",
            "udp:1.2.3.4:5",
            "udpin:0.0.0.0",
            "udpin::14550",
            "tcpout:host:99999",
            "serial:/dev/ttyUSB0",
            "serial:/dev/ttyUSB0:fast",
            "serial::57600",
            "serial:/dev/x:0",
        ] {
            assert!(
                matches!(s.parse::<LinkUrl>(), Err(LinkError::BadUrl { .. })),
                "{s} should be refused"
            );
        }
    }

    #[test]
    fn signing_key_hex() {
        let s = Signing {
            key_hex: "00112233445566778899aabbccddeeff00112233445566778899AABBCCDDEEFF".into(),
            link_id: 1,
            allow_unsigned: false,
        };
        let k = s.key().expect("valid");
        assert_eq!(k[0], 0x00);
        assert_eq!(k[1], 0x11);
        assert_eq!(k[15], 0xff);
        assert_eq!(k[31], 0xff);
        let short = Signing {
            key_hex: "abcd".into(),
            ..s.clone()
        };
        assert!(matches!(short.key(), Err(LinkError::BadSigningKey { .. })));
        let bad = Signing {
            key_hex: "zz".repeat(32),
            ..s
        };
        assert!(matches!(bad.key(), Err(LinkError::BadSigningKey { .. })));
    }
}
