// SPDX-License-Identifier: MIT
// Copyright (c) 2026 the burrforce authors

using System;
using System.Collections.Generic;
using System.Globalization;
using System.Text;

namespace Burrforce
{
    /// <summary>A small, strict JSON (RFC 8259) reader and writer for the REST plane's
    /// bodies (System.Text.Json is not in netstandard2.1, and Unity's JsonUtility cannot read
    /// free-form objects). Values: Dictionary&lt;string, object&gt;, List&lt;object&gt;, string,
    /// long (an integer literal that fits), double (any other number), bool, null.</summary>
    public static class Json
    {
        public const int MaxDepth = 64;

        /// <summary>Parses one JSON text; FormatException on anything else (trailing garbage,
        /// duplicate keys, bad escapes, depth over 64).</summary>
        public static object Parse(string text)
        {
            if (text == null) throw new ArgumentNullException("text");
            var p = new Parser(text);
            p.SkipSpace();
            object v = p.Value(0);
            p.SkipSpace();
            if (!p.AtEnd) throw p.Error("trailing characters");
            return v;
        }

        private sealed class Parser
        {
            private readonly string s;
            private int i;

            public Parser(string text) { s = text; }

            public bool AtEnd { get { return i >= s.Length; } }

            public FormatException Error(string what)
            {
                return new FormatException("JSON: " + what + " at offset " + i);
            }

            public void SkipSpace()
            {
                while (i < s.Length && (s[i] == ' ' || s[i] == '\t' || s[i] == '\n' || s[i] == '\r')) i++;
            }

            public object Value(int depth)
            {
                if (depth > MaxDepth) throw Error("nested too deeply");
                if (AtEnd) throw Error("unexpected end");
                char c = s[i];
                switch (c)
                {
                    case '{': return Obj(depth);
                    case '[': return Arr(depth);
                    case '"': return Str();
                    case 't': Literal("true"); return true;
                    case 'f': Literal("false"); return false;
                    case 'n': Literal("null"); return null;
                }
                if (c == '-' || (c >= '0' && c <= '9')) return Number();
                throw Error("unexpected character '" + c + "'");
            }

            private void Literal(string word)
            {
                if (string.CompareOrdinal(s, i, word, 0, word.Length) != 0) throw Error("bad literal");
                i += word.Length;
            }

            private Dictionary<string, object> Obj(int depth)
            {
                var d = new Dictionary<string, object>(StringComparer.Ordinal);
                i++;
                SkipSpace();
                if (i < s.Length && s[i] == '}') { i++; return d; }
                while (true)
                {
                    SkipSpace();
                    if (AtEnd || s[i] != '"') throw Error("expected a key");
                    string key = Str();
                    SkipSpace();
                    if (AtEnd || s[i] != ':') throw Error("expected ':'");
                    i++;
                    SkipSpace();
                    if (d.ContainsKey(key)) throw Error("duplicate key '" + key + "'");
                    d[key] = Value(depth + 1);
                    SkipSpace();
                    if (AtEnd) throw Error("unterminated object");
                    if (s[i] == ',') { i++; continue; }
                    if (s[i] == '}') { i++; return d; }
                    throw Error("expected ',' or '}'");
                }
            }

            private List<object> Arr(int depth)
            {
                var a = new List<object>();
                i++;
                SkipSpace();
                if (i < s.Length && s[i] == ']') { i++; return a; }
                while (true)
                {
                    SkipSpace();
                    a.Add(Value(depth + 1));
                    SkipSpace();
                    if (AtEnd) throw Error("unterminated array");
                    if (s[i] == ',') { i++; continue; }
                    if (s[i] == ']') { i++; return a; }
                    throw Error("expected ',' or ']'");
                }
            }

            private string Str()
            {
                i++;
                var sb = new StringBuilder();
                while (true)
                {
                    if (AtEnd) throw Error("unterminated string");
                    char c = s[i++];
                    if (c == '"') return sb.ToString();
                    if (c < 0x20) throw Error("control character in a string");
                    if (c != '\\') { sb.Append(c); continue; }
                    if (AtEnd) throw Error("unterminated escape");
                    char e = s[i++];
                    switch (e)
                    {
                        case '"': sb.Append('"'); break;
                        case '\\': sb.Append('\\'); break;
                        case '/': sb.Append('/'); break;
                        case 'b': sb.Append('\b'); break;
                        case 'f': sb.Append('\f'); break;
                        case 'n': sb.Append('\n'); break;
                        case 'r': sb.Append('\r'); break;
                        case 't': sb.Append('\t'); break;
                        case 'u':
                            if (i + 4 > s.Length) throw Error("short \\u escape");
                            int code;
                            if (!int.TryParse(s.Substring(i, 4), NumberStyles.AllowHexSpecifier, CultureInfo.InvariantCulture, out code))
                                throw Error("bad \\u escape");
                            sb.Append((char)code);
                            i += 4;
                            break;
                        default: throw Error("bad escape");
                    }
                }
            }

            private object Number()
            {
                int start = i;
                bool integral = true;
                if (s[i] == '-') i++;
                if (AtEnd) throw Error("bad number");
                if (s[i] == '0') i++;
                else if (s[i] >= '1' && s[i] <= '9') while (i < s.Length && char.IsDigit(s[i]) && s[i] < 128) i++;
                else throw Error("bad number");
                if (i < s.Length && s[i] == '.')
                {
                    integral = false;
                    i++;
                    int digits = i;
                    while (i < s.Length && s[i] >= '0' && s[i] <= '9') i++;
                    if (i == digits) throw Error("bad fraction");
                }
                if (i < s.Length && (s[i] == 'e' || s[i] == 'E'))
                {
                    integral = false;
                    i++;
                    if (i < s.Length && (s[i] == '+' || s[i] == '-')) i++;
                    int digits = i;
                    while (i < s.Length && s[i] >= '0' && s[i] <= '9') i++;
                    if (i == digits) throw Error("bad exponent");
                }
                string text = s.Substring(start, i - start);
                long l;
                if (integral && long.TryParse(text, NumberStyles.AllowLeadingSign, CultureInfo.InvariantCulture, out l)) return l;
                double d;
                // Mono throws OverflowException beyond ±1.8e308, .NET Core returns infinity:
                // either way it is not a number this reader can give back.
                try { d = double.Parse(text, NumberStyles.Float, CultureInfo.InvariantCulture); }
                catch (OverflowException) { throw Error("number out of range"); }
                if (double.IsInfinity(d)) throw Error("number out of range");
                // Older runtimes parse "-0.0" as +0.0; the sign of zero matters (bit-exact floats).
                if (d == 0.0 && text[0] == '-') d = -0.0;
                return d;
            }
        }

        /// <summary>JSON text of a value built from the types Parse returns (plus int, float,
        /// IDictionary&lt;string, object&gt; and IEnumerable). Non-finite doubles throw: JSON
        /// has no NaN.</summary>
        public static string Write(object value)
        {
            var sb = new StringBuilder();
            WriteTo(sb, value, 0);
            return sb.ToString();
        }

        private static void WriteTo(StringBuilder sb, object v, int depth)
        {
            if (depth > MaxDepth) throw new ArgumentException("JSON value nested too deeply");
            if (v == null) { sb.Append("null"); return; }
            if (v is string) { WriteString(sb, (string)v); return; }
            if (v is bool) { sb.Append((bool)v ? "true" : "false"); return; }
            if (v is double || v is float)
            {
                double d = Convert.ToDouble(v, CultureInfo.InvariantCulture);
                if (double.IsNaN(d) || double.IsInfinity(d)) throw new ArgumentException("JSON has no NaN or infinity");
                string t = d.ToString("R", CultureInfo.InvariantCulture);
                if (d == 0.0 && BitConverter.DoubleToInt64Bits(d) < 0) t = "-0.0"; // some runtimes drop the sign
                if (t.IndexOf('.') < 0 && t.IndexOf('E') < 0 && t.IndexOf('e') < 0) t += ".0";
                sb.Append(t);
                return;
            }
            if (v is long || v is int || v is uint || v is ulong || v is short || v is ushort || v is byte)
            {
                sb.Append(Convert.ToString(v, CultureInfo.InvariantCulture));
                return;
            }
            var dict = v as IDictionary<string, object>;
            if (dict != null)
            {
                sb.Append('{');
                bool first = true;
                foreach (var kv in dict)
                {
                    if (!first) sb.Append(',');
                    first = false;
                    WriteString(sb, kv.Key);
                    sb.Append(':');
                    WriteTo(sb, kv.Value, depth + 1);
                }
                sb.Append('}');
                return;
            }
            var list = v as System.Collections.IEnumerable;
            if (list != null)
            {
                sb.Append('[');
                bool first = true;
                foreach (object item in list)
                {
                    if (!first) sb.Append(',');
                    first = false;
                    WriteTo(sb, item, depth + 1);
                }
                sb.Append(']');
                return;
            }
            throw new ArgumentException("cannot write " + v.GetType().Name + " as JSON");
        }

        private static void WriteString(StringBuilder sb, string s)
        {
            sb.Append('"');
            foreach (char c in s)
            {
                switch (c)
                {
                    case '"': sb.Append("\\\""); break;
                    case '\\': sb.Append("\\\\"); break;
                    case '\n': sb.Append("\\n"); break;
                    case '\r': sb.Append("\\r"); break;
                    case '\t': sb.Append("\\t"); break;
                    default:
                        if (c < 0x20) sb.Append("\\u").Append(((int)c).ToString("x4", CultureInfo.InvariantCulture));
                        else sb.Append(c);
                        break;
                }
            }
            sb.Append('"');
        }

        // Typed access for callers that know the shape.

        public static Dictionary<string, object> AsObject(object v, string what)
        {
            var d = v as Dictionary<string, object>;
            if (d == null) throw new FormatException(what + " is not a JSON object");
            return d;
        }

        public static object Get(Dictionary<string, object> o, string key)
        {
            object v;
            if (!o.TryGetValue(key, out v)) throw new FormatException("JSON object has no '" + key + "'");
            return v;
        }

        public static long GetLong(Dictionary<string, object> o, string key)
        {
            object v = Get(o, key);
            if (v is long) return (long)v;
            throw new FormatException("'" + key + "' is not an integer");
        }

        public static double GetDouble(Dictionary<string, object> o, string key)
        {
            object v = Get(o, key);
            if (v is double) return (double)v;
            if (v is long) return (long)v;
            throw new FormatException("'" + key + "' is not a number");
        }

        public static string GetString(Dictionary<string, object> o, string key)
        {
            object v = Get(o, key);
            if (v == null) return null;
            var s = v as string;
            if (s == null) throw new FormatException("'" + key + "' is not a string");
            return s;
        }
    }
}
