// SPDX-License-Identifier: MIT
// Copyright (c) 2026 the burrforce authors

using System;
using System.Net;
using System.Net.Sockets;

namespace Burrforce
{
    /// <summary>A connected UDP socket to the server's endpoint: the kernel then delivers only
    /// the server's datagrams to it. Receives never block longer than asked.</summary>
    public sealed class UdpLink : IDisposable
    {
        private readonly Socket socket;

        /// <summary>ICMP "port unreachable" answers seen (nothing listening on the server's port).</summary>
        public long Unreachable { get; private set; }

        public UdpLink(string host, int port)
        {
            if (port <= 0 || port > 65535) throw new ArgumentOutOfRangeException("port");
            IPAddress address = Resolve(host);
            socket = new Socket(address.AddressFamily, SocketType.Dgram, ProtocolType.Udp);
            socket.ReceiveBufferSize = 1 << 20;
            socket.Connect(new IPEndPoint(address, port));
        }

        internal static IPAddress Resolve(string host)
        {
            IPAddress address;
            if (IPAddress.TryParse(host, out address)) return address;
            IPAddress picked = Pick(Dns.GetHostAddresses(host));
            if (picked == null) throw new ArgumentException("cannot resolve host '" + host + "'");
            return picked;
        }

        /// <summary>The address to send to among a name's addresses: the first, except that a
        /// loopback name ("localhost": ::1 first on Windows and some Linux setups) gives its
        /// IPv4 address, since servers bind 127.0.0.1 by default. UDP has no connection to
        /// fail over, so trying the addresses in turn would not reveal a wrong choice.</summary>
        internal static IPAddress Pick(IPAddress[] addresses)
        {
            IPAddress first = null, loopback4 = null;
            bool allLoopback = true;
            foreach (IPAddress a in addresses)
            {
                if (a.AddressFamily != AddressFamily.InterNetwork && a.AddressFamily != AddressFamily.InterNetworkV6) continue;
                if (first == null) first = a;
                if (!IPAddress.IsLoopback(a)) allLoopback = false;
                else if (a.AddressFamily == AddressFamily.InterNetwork && loopback4 == null) loopback4 = a;
            }
            return allLoopback && loopback4 != null ? loopback4 : first;
        }

        public void Send(byte[] datagram, int length)
        {
            try
            {
                socket.Send(datagram, 0, length, SocketFlags.None);
            }
            catch (SocketException e)
            {
                // A connected UDP socket reports an earlier ICMP error on the next call.
                if (!IsUnreachable(e)) throw;
                Unreachable++;
            }
        }

        /// <summary>Waits up to <paramref name="timeoutUs"/> (0: only what has arrived) for a
        /// datagram; returns its length, or −1 if none. The wait's resolution is the
        /// platform's (often 1 ms); a haptic loop calls this with 0.</summary>
        public int Receive(byte[] buffer, long timeoutUs)
        {
            while (true)
            {
                int micros = timeoutUs <= 0 ? 0 : (int)Math.Min(timeoutUs, int.MaxValue);
                if (socket.Available <= 0 && !socket.Poll(micros, SelectMode.SelectRead)) return -1;
                try
                {
                    return socket.Receive(buffer, 0, buffer.Length, SocketFlags.None);
                }
                catch (SocketException e)
                {
                    if (IsUnreachable(e))
                    {
                        Unreachable++;
                        if (timeoutUs <= 0) return -1;
                        continue;
                    }
                    if (e.SocketErrorCode == SocketError.WouldBlock || e.SocketErrorCode == SocketError.MessageSize)
                        return -1;
                    throw;
                }
            }
        }

        /// <summary>Sleeps until a datagram is waiting or about timeoutUs have passed (the
        /// platform's resolution, often 1 ms; 0 returns at once).</summary>
        public bool WaitReadable(int timeoutUs)
        {
            if (socket.Available > 0) return true;
            try
            {
                return socket.Poll(timeoutUs, SelectMode.SelectRead);
            }
            catch (SocketException)
            {
                return true; // a pending ICMP error: let Receive report it
            }
        }

        private static bool IsUnreachable(SocketException e)
        {
            return e.SocketErrorCode == SocketError.ConnectionRefused
                || e.SocketErrorCode == SocketError.ConnectionReset;
        }

        public void Dispose() { socket.Close(); }
    }
}
